"""
Recursive least squares on the ARX regressor: the baseline estimator.

The recursion is eqs. (47)-(50) of Ding, Chen and Qiu (2006) with an
exponential forgetting factor, written so that the covariance P stays
symmetric positive definite and cannot wind up when the data stop being
exciting.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Sequence

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.adequacy import AdequacyMonitor
from bcid_ros.estimators.base import RecursiveEstimator
from bcid_ros.estimators.change_detection import ChangeDetector, with_detector_arrays
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.recursion import (CAREFUL_GAIN, Forgetting, HEALTH_CHECK_PERIOD,
                                           RandomWalk,
                                           ls_step, ls_step_rows, LsPlants, LsSettings,
                                           repair_rows, scale_dependents)
from bcid_ros.estimators.regressor import ArxRegressor, phi_channels
from bcid_ros.estimators.residual_state import residual_items, residual_states

#: After a detected plant change the estimate restarts from at most this many of the
#: last samples (those after the change point); fewer than the detector's warm-up, so
#: that the restart cannot detect again.
RESTART_SPAN = 400
#: The restart's replay of those samples is spread over the updates (SPEC §16: no update
#: waits more than 10 ms): each update replays at most this many queued rows before its
#: own sample, and a row that decided the validity ends its slice. Measured here
#: (benchmarks/replay_stall.py, tracking cases of seeds 0-2): a replayed row costs 10-25 us
#: of CPU (rls, bcrls; orders 1-3) and a validity decision 2-3 ms, so that an update of
#: the catch-up takes at most 3.3 ms (rls) and 4.5 ms (bcrls), against 12-13 and 17-21 ms
#: replayed at once; the at most 401 rows are caught up within 10 updates (median 5).
REPLAY_SLICE = 64
#: The queue's room in a snapshot: the restart's rows, its end and the samples queued
#: behind them (fewer than these: each update replays two rows at least and queues one; a
#: detection among the samples, which the detector's warm-up all but rules out, puts at
#: most RESTART_SPAN + 1 rows ahead of them). A batched form's plant that finds its shared
#: slice spent waits before a row that would decide, for at most about half as many
#: updates as plants are catching up with it (two decide an update): room for some 700.
QUEUE_ROWS = 2 * (RESTART_SPAN + 1)
#: A queued row's last column: a sample's quiet count (>= 0; see RecursiveEstimator._learn),
#: or one of these, which keep a gap and a held sample in their place among the rows, and
#: the restart's end (after its rows: the change's reason set and the validity decided).
_GAP, _HELD, _END = -1.0, -2.0, -3.0
#: What the replay of the restart's rows has apart from what the updates show (the one-shot
#: replay's own counters, flags and reasons, which it discarded at its end).
_REPLAY_OWN = ('flags', '_updates', '_seen', '_recent', '_change_note', '_reasons',
               '_next_check')


#: No event (a mask of one False).
_NO = np.zeros(1, dtype=bool)


class LsAccessors:
    """The accessors of a least-squares state, for one plant and for K (a leading axis)."""

    @property
    def signal_scale(self) -> np.ndarray:
        """Return the scales of y, u_1 ... u_r (0 while a channel has only seen zeros)."""
        return self._signal_scale.copy()

    @property
    def initial_covariance_diagonal(self) -> np.ndarray:
        """Return the diagonal of P(0) = p0 S^-2 in the user's units."""
        return self.initial_covariance / self._component_scale ** 2

    @property
    def covariance(self) -> np.ndarray:
        """Return the covariance matrix P(t) (a copy)."""
        return self._p.copy()


class Rls(LsAccessors, RecursiveEstimator):
    r"""
    Recursive least squares with forgetting, guarded, gated and unit-free.

    For the ARX regressor :math:`\varphi(t)` of Ding et al. (2006), eqs. (53)-(55):

    .. math::

        e(t) &= y(t) - \varphi^T(t)\hat\theta(t-1) \\
        s(t) &= \lambda + \varphi^T(t) P(t-1) \varphi(t) \\
        \hat\theta(t) &= \hat\theta(t-1) + P(t-1)\varphi(t)\, e(t) / s(t)
            && \text{(47), (48)} \\
        P(t) &= \frac{1}{\lambda}\Big[P(t-1) - \frac{P(t-1)\varphi(t)\varphi^T(t)P(t-1)}{s(t)}\Big]
            && \text{(49)} \\
        J(t) &= \lambda J(t-1) + \lambda e^2(t) / s(t) && \text{(50)} \\
        \tau(t) &= \lambda \tau(t-1) + 1

    With :math:`\lambda = 1` this is exactly the paper's recursion and
    :math:`\tau(t) = t`. :math:`\tau` is the weighted sample count and
    :math:`J/\tau` the published residual variance.

    **Units.** :math:`P(0) = p_0 S^{-2}`, where :math:`S = \mathrm{diag}(s_k)`
    holds the scale of the signal in :math:`\varphi_k`: per channel (y and
    each :math:`u_i`) the smallest power of two at or above the largest
    magnitude of the first samples (those in the regressor at the first
    update; a channel that is still all zero gets its scale when it first
    is not). This is RLS on the normalised signals :math:`\varphi_k/s_k` with
    :math:`P(0) = p_0 I`, mapped back, and bit-for-bit so because the scales
    are powers of two: the estimates do not depend on the units of y and u,
    and ``initial_covariance`` is the prior variance of the parameters of
    signals of unit size.

    **Safeguards** (docs/estimators.md), each counted in :attr:`flags`:

    * the downdate is written as :math:`P - h h^T` with
      :math:`h = P\varphi/\sqrt{s}`, symmetric to the last bit;
    * anti-windup: the division by :math:`\lambda` is skipped while the
      normalised trace :math:`\mathrm{tr}(SPS)` exceeds :math:`p_0 p`
      (``windup_limited``);
    * transaction: a step with a non-finite :math:`s(t)` or :math:`e^2(t)`,
      or with :math:`s(t)/\lambda >` ``CAREFUL_GAIN`` that leaves
      :math:`SPS` numerically indefinite or conditioned beyond 1e13, is
      undone (``update_undone``) and the regressor restarts; three in a row
      mean the signal level is far from that of the first samples: the
      estimator starts afresh with new scales (``rescaled``);
    * gate: :math:`z^2 = e^2 / [(J/\tau)(1 + \varphi^T P \varphi)]`, the
      squared prediction error over its variance, goes to the rulebook's
      gate (:func:`~bcid_ros.estimators.rules.gate`: ``outlier_rejected``,
      ``plant_change``) once
      :math:`\tau \ge` ``GATE_WARMUP`` p. A detected plant change cuts the
      memory to ``CHANGE_MEMORY`` p samples: :math:`P \leftarrow P/\kappa`,
      :math:`J \leftarrow \kappa J`, :math:`\tau \leftarrow \kappa\tau`, one
      extra forgetting step that keeps :math:`J/\tau` and :math:`\tau P`;
    * every ``HEALTH_CHECK_PERIOD`` updates, and whenever :math:`s \le 0`,
      P is checked by a Cholesky factorisation and, if it has lost
      definiteness, rebuilt (``covariance_repaired``).

    **Validity**, re-evaluated every ``VALIDITY_PERIOD`` updates: the model
    :math:`A(q)` of the published estimate is unstable (a pole beyond
    ``UNSTABLE_RADIUS``) while the output power over the memory did not
    grow by ``GROWTH`` since the last check (bounded data).

    The plain step is the hot path, written here on floats and BLAS; a
    sample that needs any safeguard (a risky gain, a non-finite error, the
    gate refusing or scoring, s <= 0) goes through :func:`ls_step_rows`, the
    rules of every plant of the batched estimators, with this one plant as
    K = 1: the two take the same decisions by construction.

    Parameters
    ----------
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor, outlier_threshold
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`.
    input_delay, detrend, adapt
        See :class:`~bcid_ros.estimators.base.RecursiveEstimator`; a dead time
        delays the input lags of phi (docs/estimators.md, "Dead time").

    """

    name = 'rls'
    noise_names = ('residual_variance',)
    tracks = True
    #: The residual the model says is white, for the residual tests
    #: (:data:`~bcid_ros.estimators.adequacy.MODEL_TESTS`): the equation error.
    adequacy_model = 'arx'
    #: Whether the published std is the HAC sandwich of the equation error's scores.
    hac_std = True

    def __init__(self, **settings: Any) -> None:
        super().__init__(**settings)
        self._regressor = ArxRegressor(self.order, self.num_inputs, self.feedthrough,
                                       self.input_delay)
        #: What happens to P between samples: recursion.Forgetting (P / lambda, anti-windup)
        #: or, with adaptation: kalman, recursion.RandomWalk (P + q S^-2)
        self._propagation = (RandomWalk(self._parameter_drift) if self.adaptation == 'kalman'
                             else Forgetting(self.initial_covariance * self.num_parameters))
        self._channel = phi_channels(self.order, self.num_inputs, self.feedthrough)
        self._detector = ChangeDetector()
        self._relearned = 0
        self._checks = 0
        #: This plant's place in the validity period: a restart's decisions come this many
        #: updates early (0 here; a batched form's plant k of K: k·100/K, BatchedRls.reset)
        self._check_offset = 0
        self._clear_queue()
        self._reset()

    # ------------------------------------------------------------- the step
    def _update(self, y: float, u: np.ndarray) -> None:
        if self._queue.shape[0]:  # a restart's rows are still being replayed: this joins them
            self._catch_up(y, u)
            return
        self._step_sample(y, u)

    def _step_sample(self, y: float, u: np.ndarray) -> None:
        """Take one sample: remember it, push it, and step on a ready regressor."""
        if self._change_detection:
            self._remember(y, u)
        phi = self._regressor.push(y, u)
        if self._scales_pending and self._regressor.ready:
            self._choose_scales()
        if self._regressor.ready and self._ls_step(y, phi):
            self._after_step(y, u, phi)

    def _after_step(self, y: float, u: np.ndarray, phi: np.ndarray) -> None:
        """Follow a committed step: the subclass's part, the trust monitors, the validity."""
        self._after_ls_step(y, phi)
        if self._tau >= self._gate_from and not self._quiet_left:
            self._simulation.record(y, u)
            self._record_residual(y, phi, u)
        else:  # a sample the window does not take is a gap in it (docs/trust.md)
            self._simulation.gap()
        if self._updates >= self._next_check:
            self._check_validity()

    #: _ls_step checks before it commits: the cheap form of the transaction.
    _guarded_update = _update

    def _block_step(self, rows: np.ndarray) -> Callable[[float, np.ndarray], None]:
        """
        Return the function that takes each row of a checked block (see the base class).

        When the rows would go straight to the step with a filled regressor
        and chosen scales, their regressors are formed for the block at once
        (:meth:`ArxRegressor.push_rows`) and each row takes only the step: the
        same phi(t), so the same estimate, without a push and its checks per row. The
        regressor is then ahead of the rows until the block is done, which no
        step reads: a refused step only clears it (:meth:`_undo`), and the rows
        after that go sample by sample into the empty regressor, as they would
        have; the rescaling that reads it needs two undone steps in a row
        before it, so a block that starts after one goes sample by sample. A
        row that raises ends the block, and its caller restarts the regressor.
        """
        update = super()._block_step(rows)
        regressor = self._regressor
        if (update != self._guarded_update or self._scales_pending or not regressor.ready
                or self._undone_in_row or self._queue.shape[0]):
            return update
        regressors = iter(regressor.push_rows(rows))
        refused_before, relearned_before = self._refused, self._relearned

        def step(y: float, u: np.ndarray) -> None:
            phi = next(regressors)
            if self._refused != refused_before or self._relearned != relearned_before:
                # a refusal restarted the regressor, or a plant change refilled it
                self._update(y, u)
                return
            if self._change_detection:
                self._remember(y, u)
            if self._ls_step(y, phi):
                self._after_step(y, u, phi)

        return step

    def _hold(self, y: float, u: np.ndarray) -> None:
        """Move the regressor on without a step: theta, P, J and tau stay as they are."""
        if self._queue.shape[0]:  # after the rows still to replay, in its place
            self._catch_up(y, u, _HELD)
            return
        self._hold_sample(y, u)

    def _hold_sample(self, y: float, u: np.ndarray) -> None:
        self._regressor.push(y, u)
        self._simulation.gap()  # the held samples are not recorded

    def _after_ls_step(self, y: float, phi: np.ndarray) -> None:
        """Extend the LS step on (y, phi) (the bias compensation of subclasses); nothing here."""

    def _record_residual(self, y: float, phi: np.ndarray, u: np.ndarray) -> None:
        """
        Give the residual tests and the HAC covariance this step's equation error.

        From the gate's warm-up on (tau >= GATE_WARMUP p), as the gate: the
        a-priori errors of the first, converging steps are correlated with the
        inputs by design (docs/trust.md). Not while a huge value (beyond
        2^450) is in the regressor: its products would overflow the tests' sums.
        """
        error = self._error
        self._monitor.record(error, u)
        # the score phi e of the estimating equations sum_t w_t phi (y - phi' theta) = 0
        self._hac.record_product(phi, error)
        if self._gain:  # e / sqrt(s): the normalised one-step error (none after a rare step)
            self._detect(error / math.sqrt(self._gain))

    def _remember(self, y: float, u: np.ndarray) -> None:
        """Keep the sample among the last RESTART_SPAN (for a restart after a change; on)."""
        row = self._recent[self._seen % RESTART_SPAN]
        row[0] = y
        row[1:] = u
        self._seen += 1

    def _detect(self, error: float) -> None:
        """Give the change detector this sample's normalised error; restart on a change."""
        if self._change_detection:
            age = self._detector.record(error)
            if age:
                self._plant_changed(age)

    def _plant_changed(self, age: int) -> None:
        """
        Restart from the ``age`` samples after the detected change point (docs/tracking.md).

        The estimate starts afresh (P(0), J = tau = 0, the residual tests and
        the compensation of subclasses anew; the signal scales and the
        estimate as the prior mean kept) and learns again from the samples
        after the change point (at most RESTART_SPAN): the memory of the old
        plant is cut, not blended in. Not valid from this sample on, with the
        reason, until the new estimate passes the residual tests.

        The samples are queued here and replayed over the next updates, at
        most ``REPLAY_SLICE`` in each (:meth:`_catch_up`), each update's own
        sample joining the queue's end: the same rows in the same order as
        replayed at once, so the estimate once caught up is the one-shot's
        bit for bit (:meth:`_finish_catch_up` replays them at once). The
        replay keeps its own counters, flags and reasons (``_REPLAY_OWN``),
        which the one-shot replay discarded at its end: the updates meanwhile
        show this sample's flag and reason, the sample counts of before, and
        this sample's estimate (theta, the uncompensated, the noise; the
        covariance is the replay's), not valid.
        """
        self._flag('plant_change')
        first = self._seen - age + 1  # in the samples the estimator was given, from 1
        count = min(age + self._regressor.span, RESTART_SPAN, self._seen)
        rows = self._recent[(np.arange(self._seen - count, self._seen)) % RESTART_SPAN]
        theta, scale = self._theta_ls.copy(), self._signal_scale.copy()
        # the estimate published until caught up: this sample's (not valid), not a replay's
        # of a few rows (theta, the estimate before compensation, the noise)
        self._shown = (self._theta().copy(), self._theta_uncompensated().copy(),
                       np.array(self._noise(), dtype=float))
        shown = {name: getattr(self, name) for name in _REPLAY_OWN}
        shown['flags'] = dict(self.flags)
        self._reset()  # (a new ring: the replay remembers its rows in it, as before)
        self._signal_scale = scale
        self._set_scale_dependents()
        self._p = self._initial_p()
        self._theta_ls[:] = theta
        self._relearned += 1
        # the replay's own start: the flags so far (bcrls reads its resets' count), the rest
        # as _reset left them; what the updates show until the replay's end: as before it
        self._replay_own = {name: getattr(self, name) for name in _REPLAY_OWN}
        self._replay_own['flags'] = dict(shown['flags'])
        for name, value in shown.items():
            setattr(self, name, value)
        self._restart_note = self._change_note = f'plant changed (sample {first})'
        self._reasons = (self._restart_note,)
        self._next_check = self._updates + rules.VALIDITY_PERIOD  # (the replay's end decides)
        # the rows first, then those queued after this detection's sample (during a catch-up)
        queued = np.zeros((count + 1, self._queue.shape[1]))
        queued[:-1, :-1] = rows
        queued[-1, -1] = _END
        self._queue = np.concatenate([queued, self._queue])
        self._restart_left = count

    def _catch_up(self, y: float, u: np.ndarray, kind: float | None = None) -> None:
        """Replay at most ``_replay_slice`` queued rows, then take this sample (or queue it)."""
        self._replay(self._replay_slice)
        if not self._queue.shape[0]:  # caught up: the sample is taken as any other
            if kind == _HELD:
                self._hold_sample(y, u)
            else:
                self._step_sample(y, u)
            return
        row = np.empty((1, self._queue.shape[1]))
        row[0, 0], row[0, 1:-1] = y, u
        row[0, -1] = self._quiet_left if kind is None else kind
        self._queue = np.concatenate([self._queue, row])

    def _finish_catch_up(self) -> None:
        """Replay every queued row now (the one-shot restart)."""
        while self._queue.shape[0]:
            self._replay(self._queue.shape[0])

    def restart_regressor(self) -> None:
        """Forget the sample history (after a gap); during a catch-up, after the queued rows."""
        if self._queue.shape[0]:
            row = np.zeros((1, self._queue.shape[1]))
            row[0, -1] = _GAP
            self._queue = np.concatenate([self._queue, row])
            return
        super().restart_regressor()

    def reset(self) -> None:
        """Return to the state right after construction (no rows queued)."""
        self._clear_queue()
        super().reset()

    def _clear_queue(self) -> None:
        self._queue = np.zeros((0, 2 + self.num_inputs))  # [y, u, quiet count or _GAP/_HELD]
        self._restart_left = 0
        self._restart_note = ''
        self._replay_own = self._fresh_replay_own()
        self._shown: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _fresh_replay_own(self) -> dict[str, Any]:
        """Return the replay's own values of an estimator with no restart under way."""
        return {'flags': {}, '_updates': 0, '_seen': 0,
                '_recent': np.zeros((RESTART_SPAN, 1 + self.num_inputs)),
                '_change_note': '', '_reasons': (), '_next_check': 0}

    def _replay(self, limit: int) -> None:
        """
        Replay at most ``limit`` queued rows, oldest first, and at most one validity decision.

        The restart's rows run with the replay's own counters, flags and
        reasons swapped in, as the one-shot replay ran (quiet, warnings
        silenced); the row after them (``_END``) sets the change's reason and
        decides the validity, as after it. The rows queued behind are the
        updates' own samples, taken as they would have been (a detection
        among them restarts again, its rows ahead of the rest). A validity
        decision costs as much as some 60 rows (bcrls: the residual tests and
        the simulation check, about 2-3 ms here), so a row that made one ends
        the slice. Refused rows do not count in the refusals the operating
        point follows: its means took the samples when they came. Without
        ``_replay_decides`` (a batched form's plant whose turn found the
        shared slice spent) the replay stops before a row that would decide.
        """
        refused, quiet, checks = self._refused, self._quiet_left, self._checks
        shown, self._shown = self._shown, None  # (the rows see the estimate they make)
        done = 0
        with np.errstate(all='ignore'):
            # (two rows at least: the queue shrinks even if each row decides, an outlier's)
            while done < limit and self._queue.shape[0] and (
                    self._checks == checks or done < 2):
                if self._restart_left:
                    replayed = self._replay_restart_rows(limit - done, checks, done)
                    done += replayed
                    if replayed:
                        continue
                    break
                row = self._queue[0]
                if not self._replay_decides and (row[-1] == _END or self._decides_next()):
                    break
                self._queue = self._queue[1:]
                self._replay_queued_row(row)
                done += 1
        self._refused, self._quiet_left = refused, quiet
        if not self._queue.shape[0]:
            self._shown = None
        elif self._shown is None:  # (else a detection among the rows showed its own)
            self._shown = shown

    def _replay_restart_rows(self, limit: int, checks: int, done: int) -> int:
        """Replay at most ``limit`` of the restart's rows (to a validity decision); count them."""
        self._swap_replay_own()
        self._quiet_left = 0
        start = done
        while done - start < limit and self._restart_left and (
                self._checks == checks or done < 2):
            if not self._replay_decides and self._decides_next():
                break
            row = self._queue[0]
            self._queue = self._queue[1:]
            self._restart_left -= 1
            self._step_sample(float(row[0]), row[1:-1])
            done += 1
        self._swap_replay_own()
        return done - start

    def _decides_next(self) -> bool:
        """Whether the next update that steps makes the periodic validity decision."""
        return self._updates + 1 >= self._next_check

    def _swap_replay_own(self) -> None:
        own = self._replay_own
        for name in _REPLAY_OWN:
            own[name], value = getattr(self, name), own[name]
            setattr(self, name, value)

    def _replay_queued_row(self, row: np.ndarray) -> None:
        """Take a queued row after the restart's: its end, or an update's sample, gap or hold."""
        y, u, kind = float(row[0]), row[1:-1], float(row[-1])
        if kind == _END:
            # the replay's end: its counters, flags and ring gone (_REPLAY_OWN), its reasons
            # replaced by the change's until the new estimate passes its checks
            self._change_note = self._restart_note
            # plants of a batched form restarting in one frame would decide together from
            # here on, the replay's own decisions having spent the phase
            self._check_phase = self._check_offset
            self._check_validity()
        elif kind == _GAP:
            self._restart_regressor()
        elif kind == _HELD:
            self._hold_sample(y, u)
        else:
            self._quiet_left = int(kind)
            self._step_sample(y, u)

    @property
    def catching_up(self) -> int:
        """Count the rows still queued after a detected change (0: caught up)."""
        return int(self._queue.shape[0])

    #: The rows an update replays at most while catching up (:meth:`_catch_up`). The
    #: batched estimators share REPLAY_SLICE among their plants catching up at once; the
    #: rows and their order are the same whatever the slice, so is the estimate caught up.
    _replay_slice = REPLAY_SLICE
    #: Whether a replay's slice may make a validity decision (the batched forms' plants
    #: whose turn finds their shared slice spent may not: :meth:`_replay`).
    _replay_decides = True

    #: Not valid while a restart's rows are queued (:meth:`_live_reasons`).
    _LIVE_REASONS = True

    def _live_reasons(self) -> tuple[str, ...]:
        """Return the change's reason while its rows are still queued, where not decided yet."""
        if self._queue.shape[0] and self._restart_note not in self._reasons:
            return (self._restart_note,)
        return ()

    def _ls_step(self, y: float, phi: np.ndarray) -> bool:
        """Do the RLS step (47)-(50) on a ready regressor ``phi``; return whether it did."""
        lam = self._forgetting_factor
        g = self._p.dot(phi)
        s = lam + float(phi.dot(g))
        e = y - float(phi.dot(self._theta_ls))
        if not (s < CAREFUL_GAIN * lam and e * e < math.inf and s > 0.0):
            return self._rare_step(y, phi)
        tau = self._tau
        if tau >= self._gate_from:
            # the gate's quiet case (rules.gate_is_quiet) written out on floats: used, and
            # only a lifted tail moves; any other tested sample goes to the rules
            if self._change_score or not e * e / ((self._loss / tau + self._variance_floor)
                                                  * (s + 1.0 - lam)) <= self._gate_limit2:
                return self._rare_step(y, phi)
            if self._gate_tail != 1.0:
                self._gate_tail = rules.lowered_tail(self._gate_tail)
        self._error = e
        self._gain = s
        self._p = ls_step(self._theta_ls, self._p, g, s, e)
        # J(t) = lambda J(t-1) + lambda e^2 / s ; tau(t) = lambda tau(t-1) + 1
        self._loss = lam * (self._loss + e * e / s)
        self._tau = lam * tau + 1.0
        if self._propagation.propagate_one(self._p, lam, self._trace_weights):
            self._flag('windup_limited')
        self._updates += 1
        if self._updates % HEALTH_CHECK_PERIOD == 0:
            self._check_covariance()
        self._undone_in_row = 0
        return True

    def _rare_step(self, y: float, phi: np.ndarray) -> bool:
        """Do the step by :func:`ls_step_rows` (this plant as K = 1); return whether it did."""
        plants = self._as_plants()
        outcome = ls_step_rows(plants, np.zeros(1, dtype=np.intp), np.array([y]), phi[None],
                               self._ls_settings())
        self._take_scalars(plants)
        self._error = float(outcome.errors[0])
        self._gain = 0.0
        for key, where in outcome.events.items():
            if where[0]:
                self._flag(key)
        changed = bool(outcome.events.get('plant_change', _NO)[0])
        if changed:  # the gate's (three refusals in a row): the memory was cut
            self._forget_residuals()
            # (the samples given are counted while detection runs; else the updates)
            sample = self._seen if self._change_detection else self._updates
            self._change_note = f'plant changed (sample {sample})'
        if outcome.restart[0]:
            self._refused += 1
            self._restart_regressor()
        if outcome.relearn[0]:
            self._restart_learning()
        if changed or outcome.events.get('outlier_rejected', _NO)[0]:
            # valid is decided at every such event, not only every VALIDITY_PERIOD updates
            self._check_validity()
        return bool(outcome.stepped[0])

    def _as_plants(self) -> LsPlants:
        """Return this estimator's LS state as one plant (views of theta and P)."""
        return LsPlants(self._theta_ls[None], self._p[None], np.array([self._loss]),
                        np.array([self._tau]), np.array([self._updates]),
                        np.array([self._undone_in_row]), np.array([self._change_score]),
                        np.array([self._gate_tail]), np.array([self._variance_floor]),
                        self._component_scale[None])

    def _take_scalars(self, plants: LsPlants) -> None:
        """Take back the scalars of :meth:`_as_plants` (theta and P were views)."""
        self._loss, self._tau = float(plants.loss[0]), float(plants.tau[0])
        self._updates, self._undone_in_row = int(plants.updates[0]), int(plants.undone[0])
        self._change_score, self._gate_tail = float(plants.score[0]), float(plants.tail[0])

    def _ls_settings(self) -> LsSettings:
        return LsSettings(self._forgetting_factor, self._gate_limit2, self._gate_from,
                          self._propagation, self.initial_covariance)

    def _restart_learning(self) -> None:
        """Start afresh with scales chosen from the samples now in the regressor."""
        self._flag('rescaled')
        regressor = self._regressor
        history, filled, position = regressor.history.copy(), regressor.filled, \
            regressor.position
        self._reset()
        regressor.history[:] = history
        regressor.filled, regressor.position = filled, position
        self._choose_scales()

    def _check_covariance(self) -> None:
        """Repair P if it lost definiteness (the health check of the plain step)."""
        if not rules.definite(self._p[None])[0]:
            self._repair_covariance()

    def _repair_covariance(self) -> None:
        """Rebuild P as the nearest symmetric positive definite matrix."""
        self._flag('covariance_repaired')
        repair_rows(self._as_plants(), np.zeros(1, dtype=np.intp), self.initial_covariance)

    # ------------------------------------------------------------ the units
    def _initial_p(self) -> np.ndarray:
        """Return P(0) = p0 S^-2 for the current scales."""
        return np.diag(self.initial_covariance / self._component_scale ** 2)

    def _choose_scales(self) -> None:
        """Give each channel still without a scale the one of the data in the regressor."""
        new = rules.choose_scales(self._signal_scale[None], self._regressor.peaks()[None])
        rules.rescale_new_channels(self._p[None], new, self._signal_scale[None], self._channel)
        self._set_scale_dependents()

    def _set_scale_dependents(self) -> None:
        self._scales_pending = bool((self._signal_scale == 0.0).any())
        component, floor = scale_dependents(self._signal_scale[None], self._channel)
        self._component_scale, self._variance_floor = component[0], float(floor[0])
        self._trace_weights = self._component_scale ** 2

    # --------------------------------------------------------- the validity
    def _check_validity(self, more: Sequence[str] = ()) -> None:
        """
        Decide the reasons (every VALIDITY_PERIOD updates; see the class docstring).

        Own reasons: an unstable model while the output power is bounded,
        then ``more`` (a subclass's); the base class adds the shared ones.
        The growth test's memory moves on after the decision.
        """
        self._next_check = self._updates + rules.VALIDITY_PERIOD - self._check_phase
        self._check_phase = 0
        self._checks += 1  # (not state: a replay's slice ends at a decision)
        with np.errstate(all='ignore'):
            power = rules.output_powers(self._p[None], np.array([self._tau]), self.order)
            own = rules.unstable_models(self._theta()[None, :self.order], power,
                                        np.array([self._last_power]))[0]
        # a plant change's reason holds until the new estimate passes its checks
        self._change_note = self._decide_validity(own + list(more), self._change_note)
        self._last_power = float(power[0])

    # --------------------------------------------------------- the accessors
    @property
    def ready(self) -> bool:
        """Whether phi(t) is filled and at least p updates have been made."""
        return self._updates >= self.num_parameters

    @property
    def samples(self) -> int:
        """Count the estimator updates (samples with a filled regressor)."""
        return self._updates

    @property
    def covariance_trace(self) -> float:
        """Return tr P(t)."""
        return float(np.trace(self._p))

    @property
    def loss(self) -> float:
        """Return the weighted loss J(t) of eq. (50)."""
        return self._loss

    @property
    def weighted_count(self) -> float:
        """Return tau(t) = sum of lambda^(t-i); equals t when lambda = 1."""
        return self._tau

    # ------------------------------------------------------- the uncertainty
    def _parameter_covariance(self) -> np.ndarray | None:
        r"""
        Return the HAC sandwich covariance of the LS estimate (None before its first block).

        The LS estimate solves :math:`\sum_t w_t\varphi_t(y_t - \varphi_t^T\theta) = 0`,
        so :math:`\hat\theta - \theta \approx P\sum_t w_t\varphi_t e_t` and its
        covariance is :math:`P\,\mathrm{var}(\sum_t w_t s_t)\,P` with the scores
        :math:`s_t = \varphi_t e_t`. :class:`~bcid_ros.estimators.hac.HacCovariance`
        estimates the middle from the scores' lagged products, prewhitened and
        windowed (Andrews 1991; Andrews and Monahan 1992): calibrated whether
        the equation error is white (an ARX plant) or coloured (docs/trust.md).
        The scores count from the gate's warm-up on; the first block of 64
        gives the first covariance.
        """
        if self._updates < self.num_parameters:
            return None
        return self._hac.covariance(self._p)

    def _theta(self) -> np.ndarray:
        return self._theta_ls if self._shown is None else self._shown[0]

    def _theta_uncompensated(self) -> np.ndarray:
        return self._theta_ls if self._shown is None else self._shown[1]

    def _noise(self) -> np.ndarray:
        if self._shown is not None:
            return self._shown[2]
        return np.array([self._loss / self._tau if self._tau > 0 else 0.0])

    # -------------------------------------------------------------- the state
    def _reset(self) -> None:
        p = self.num_parameters
        self._regressor.clear()
        self._theta_ls = np.zeros(p)
        self._p = self.initial_covariance * np.eye(p)
        self._loss = 0.0
        self._tau = 0.0
        self._updates = 0
        self._signal_scale = np.zeros(1 + self.num_inputs)
        self._set_scale_dependents()
        self._gate_from = rules.GATE_WARMUP * p
        self._undone_in_row = 0
        self._next_check = p
        #: Updates by which the decision after the first comes early (once): the offset,
        #: so that plants restarting in one frame of a batched form still decide apart
        self._check_phase = self._check_offset
        self._last_power = math.inf
        self._reasons: tuple[str, ...] = ()
        self._error = 0.0
        self._gain = 0.0
        # the last RESTART_SPAN samples as the step took them, for a restart after a change;
        # part of the state, so a reset empties it
        self._recent = np.zeros((RESTART_SPAN, 1 + self.num_inputs))
        self._seen = 0
        self._change_note = ''
        self._detector.clear()
        self._forget_residuals()

    def _forget_residuals(self) -> None:
        """Start the residual tests, the HAC and the simulation check afresh (reset, change)."""
        self._start_simulation_check()
        self._monitor = AdequacyMonitor(num_inputs=self.num_inputs, model=self.adequacy_model,
                                        forgetting_factor=self._forgetting_factor)
        self._hac = (HacCovariance(dimension=self.num_parameters,
                                   forgetting_factor=self._forgetting_factor)
                     if self.hac_std else None)

    def _restart_regressor(self) -> None:
        self._regressor.clear()
        self._simulation.clear()  # (a gap in its window)

    def _state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        arrays = {'theta_ls': self._theta_ls, 'p': self._p,
                  'history': self._regressor.history, 'signal_scale': self._signal_scale}
        scalars = {'loss': self._loss, 'tau': self._tau, 'updates': self._updates,
                   'filled': self._regressor.filled,
                   'position': self._regressor.position,
                   'forgetting_factor': self._forgetting_factor,
                   'undone_in_row': self._undone_in_row, 'next_check': self._next_check,
                   'check_phase': self._check_phase, 'check_offset': self._check_offset,
                   'last_power': self._last_power, 'reasons': self._reasons,
                   'seen': self._seen, 'change_note': self._change_note}
        residual_arrays, residual_scalars = residual_items(
            self._monitor.get_state(), None if self._hac is None else self._hac.get_state())
        replay_arrays, replay_scalars = self._replay_items()
        return ({**arrays, **residual_arrays, **self._detector.get_state(),
                 'recent': self._recent, **replay_arrays},
                {**scalars, **residual_scalars, **replay_scalars})

    def _replay_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return the queued rows (in a fixed-size array) and the replay's own values."""
        arrays, scalars = caught_up_items(self.num_inputs, self.num_parameters,
                                          len(self.noise_names))
        if not self._queue.shape[0]:  # (what the last replay left is never read again)
            return arrays, scalars
        arrays['replay_queue'][:self._queue.shape[0]] = self._queue
        own = self._replay_own
        arrays.update(shown_theta=self._shown[0], shown_theta_uncompensated=self._shown[1],
                      shown_noise=self._shown[2])
        scalars.update(
            replay_queued=self._queue.shape[0], restart_left=self._restart_left,
            restart_note=self._restart_note, replay_flags=dict(own['flags']),
            replay_updates=own['_updates'], replay_seen=own['_seen'],
            replay_change_note=own['_change_note'], replay_reasons=own['_reasons'],
            replay_next_check=own['_next_check'])
        return arrays, scalars

    def _load_replay(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take the queued rows and the replay's own values of a snapshot (none: caught up)."""
        self._clear_queue()
        queued = int(scalars.get('replay_queued', 0))
        if not queued:
            return
        restart_left = int(scalars['restart_left'])
        if not (restart_left < queued <= arrays['replay_queue'].shape[0]):
            # (the restart's rows and their end are in the queue: a snapshot that says
            # otherwise would stop the replay at its first slice)
            raise ValueError(f'the restart replay state is inconsistent: {queued} rows '
                             f'queued, {restart_left} of them the restart\'s')
        self._queue = np.array(arrays['replay_queue'][:queued], dtype=float)
        self._restart_left = restart_left
        self._restart_note = str(scalars['restart_note'])
        self._replay_own = {
            'flags': dict(scalars['replay_flags']), '_updates': int(scalars['replay_updates']),
            '_seen': int(scalars['replay_seen']),
            # (the ring the replay remembers its rows in is never read: not kept)
            '_recent': np.zeros((RESTART_SPAN, 1 + self.num_inputs)),
            '_change_note': str(scalars['replay_change_note']),
            '_reasons': tuple(scalars['replay_reasons']),
            '_next_check': int(scalars['replay_next_check'])}
        self._shown = tuple(np.array(arrays[key], dtype=float) for key in (
            'shown_theta', 'shown_theta_uncompensated', 'shown_noise'))

    def set_state(self, state: Any) -> None:
        """Restore a :meth:`get_state` snapshot; one from before the detector loads too."""
        own, _ = self._state_items()
        arrays = with_detector_arrays(state.arrays, own)
        for key in ('recent', 'replay_queue', 'shown_theta',
                    'shown_theta_uncompensated', 'shown_noise'):  # (older snapshots: none)
            if key not in arrays:
                arrays = {**arrays, key: np.zeros_like(own[key])}
        super().set_state(dataclasses.replace(state, arrays=arrays))

    def _load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        self._theta_ls = arrays['theta_ls']
        self._p = arrays['p']
        self._regressor.history[:] = arrays['history']
        self._signal_scale = arrays['signal_scale']
        self._set_scale_dependents()
        self._regressor.filled = int(scalars['filled'])
        self._regressor.position = int(scalars['position'])
        self._loss = float(scalars['loss'])
        self._tau = float(scalars['tau'])
        self._updates = int(scalars['updates'])
        self._forgetting_factor = float(scalars['forgetting_factor'])
        self._undone_in_row = int(scalars['undone_in_row'])
        self._next_check = int(scalars['next_check'])
        self._check_phase = int(scalars.get('check_phase', 0))  # (older snapshots: none)
        self._check_offset = int(scalars.get('check_offset', 0))
        self._last_power = float(scalars['last_power'])
        self._reasons = tuple(scalars['reasons'])
        self._seen = int(scalars.get('seen', 0))
        self._change_note = str(scalars.get('change_note', ''))
        self._recent[:] = arrays['recent']
        self._load_replay(arrays, scalars)
        self._detector.set_state(arrays)
        monitor, hac = residual_states(arrays, scalars)
        self._monitor.set_state(monitor)
        if self._hac is not None:
            self._hac.set_state(hac)


def caught_up_items(num_inputs: int, num_parameters: int, noises: int,
                    ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Return the snapshot items of a restart's replay of an estimator with no rows queued."""
    return {'replay_queue': np.zeros((QUEUE_ROWS, 2 + num_inputs)),
            'shown_theta': np.zeros(num_parameters),
            'shown_theta_uncompensated': np.zeros(num_parameters),
            'shown_noise': np.zeros(noises)}, {
        'replay_queued': 0, 'restart_left': 0, 'restart_note': '', 'replay_flags': {},
        'replay_updates': 0, 'replay_seen': 0, 'replay_change_note': '', 'replay_reasons': (),
        'replay_next_check': 0}


def ls_batch(y: np.ndarray, u: np.ndarray, *, order: int, num_inputs: int = 1,
             feedthrough: bool = False, initial_covariance: Any = None,
             forgetting_factor: float = 1.0,
             input_delay: Any = None) -> tuple[np.ndarray, np.ndarray, float, float]:
    r"""
    Solve the (weighted, regularised) least-squares problem that :class:`Rls` solves recursively.

    .. math::

        \hat\theta_{LS}(N) = \Big[\lambda^{N'} P_0^{-1} + \sum_i \lambda^{N'-i}\varphi(i)
            \varphi^T(i)\Big]^{-1} \sum_i \lambda^{N'-i}\varphi(i) y(i)

    over the N' = N - n - max(d_i) updates that have a filled regressor, with
    :math:`P_0 = \mathrm{diag}(` ``initial_covariance`` :math:`)` (a scalar
    or the p diagonal entries, e.g. :attr:`Rls.initial_covariance_diagonal`).
    With ``initial_covariance=None`` the :math:`P_0^{-1}` term is dropped
    (plain LS).

    Parameters
    ----------
    y : numpy.ndarray, shape ``(N,)``
        Outputs.
    u : numpy.ndarray, shape ``(N,)`` or ``(N, r)``
        Inputs.
    order, num_inputs, feedthrough, initial_covariance, forgetting_factor
        As for :class:`Rls`.
    input_delay : sequence of int, optional
        Dead time d_i of each input (None: none).

    Returns
    -------
    theta : numpy.ndarray, shape ``(p,)``
        The LS estimate.
    p : numpy.ndarray, shape ``(p, p)``
        The inverse of the (regularised) weighted information matrix.
    loss : float
        J = weighted sum of squared residuals at theta.
    tau : float
        Weighted sample count sum(lambda^(N'-i)).

    """
    y = np.asarray(y, dtype=float).reshape(-1)
    u = np.asarray(u, dtype=float).reshape(y.shape[0], -1)
    regressor = ArxRegressor(order, num_inputs, feedthrough, input_delay)
    phi = regressor.regressors(y, u)
    target = y[regressor.span:]
    weights = forgetting_factor ** np.arange(phi.shape[0] - 1, -1, -1, dtype=float)
    information = (phi * weights[:, None]).T @ phi
    if initial_covariance is not None:
        prior = np.broadcast_to(np.asarray(initial_covariance, dtype=float), (phi.shape[1],))
        information += np.diag(forgetting_factor ** phi.shape[0] / prior)
    theta = np.linalg.solve(information, (phi * weights[:, None]).T @ target)
    residual = target - phi @ theta
    return theta, np.linalg.inv(information), float(weights @ residual ** 2), float(
        weights.sum())
