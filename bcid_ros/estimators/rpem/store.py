r"""
The samples RPEM stores for its batch fits, and the schedule of the fits.

The recursion never starts cold (docs/estimators.md, "RPEM", "The start"):
the samples are kept, on the raw operating point, in a ring of the last
``BATCH_LIMIT``, with the start of each gap-free segment (a break: a held or
refused sample, a restart of the regressor, a plant change) and the samples
no fit may weigh (an output the gate refused, an outlier a fit found). After
``max(FIRST_FIT_SAMPLES, FIRST_FIT_PER_PARAMETER p)`` of them, and again each
time their count has grown by ``FIT_GROWTH`` up to ``BATCH_LIMIT`` (then, with
forgetting, every ``SLIDE`` samples on the last ``BATCH_LIMIT``; after a plant
change only the samples after its change point count),
:meth:`SampleStore.start` fits them with
:class:`~bcid_ros.estimators.rpem.fit.BatchFit` (Ljung, *System
Identification*, 2nd ed., 1999, ch. 10): centred on the current means, in
the units of one power of two per channel at or above its robust size
(:func:`signal_size`, :func:`~bcid_ros.estimators.rules.powers_of_two_at_least`),
sample t of T weighing :math:`\lambda^{T-1-t}`; the samples the fit's
prediction errors mark as outliers are then taken out and the fit repeated.

**A fit spread over updates.** A :class:`FitJob` holds a copy of what one
fit needs (the rows as stored when it was due, the current estimate, the
means and scales) and runs the fit's passes (:meth:`BatchFit.steps`) a
bounded amount of work at a time (:meth:`FitJob.advance`): each pass's cost
is announced before it runs, and an update runs the passes that fit in
``SLICE`` sample-columns (the first whatever its cost), so that no update
waits on a whole fit nor overruns its slice by a pass. After the fit, the
job's passes make what the recursion takes from it beside the estimate
(:class:`FitUncertainty`: P, the HAC of the fit's scores, the root of its
initial states' share), so that the hand-off only installs them. Its result
is taken at the update of the job's last pass, the hand-off, with the
predictor run on over the samples stored since (:meth:`BatchFit.continued`).
The work is counted, not timed: the same samples give the same hand-off,
bit for bit, in a node and in a replay, and a restored snapshot runs the
same passes again to the work done.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.hac import HacCovariance
from bcid_ros.estimators.rpem.fit import BatchFit, FitResult, PASS_COST, Steps
from bcid_ros.estimators.rpem.uncertainty import (fitted_scores, normalised_covariance,
                                                  profiled_excess, score_hac, with_unresolved)

#: The first batch fit waits for this many usable samples (at least) ...
FIRST_FIT_SAMPLES = 50
#: ... and for this many per parameter.
FIRST_FIT_PER_PARAMETER = 10
#: The batch fit is repeated each time the stored samples grow by FIT_GROWTH, up to
#: BATCH_LIMIT samples.
FIT_GROWTH = 1.5
#: See FIT_GROWTH.
BATCH_LIMIT = 8192
#: With forgetting, fits continue every SLIDE samples beyond BATCH_LIMIT (on the last
#: BATCH_LIMIT samples).
SLIDE = BATCH_LIMIT // 2
#: A fit excludes the samples whose prediction error exceeds the gate's limit
#: (robust scale) when they are at most this share of the stored samples.
OUTLIER_SHARE = 0.05

#: The work of a fit done per update (sample-columns of its passes, BatchFit.steps): about
#: 2 ms on one core of the development machine, 2.5 ms on the 2-vCPU one of session 11. An
#: update runs only the passes that fit in it, or one larger pass (at most BATCH_LIMIT
#: samples of a gradient, 2 (p + 1) columns: 3.2 ms there at p = 4; or the hand-off). A fit
#: of 8192 samples of a second-order plant is about 40 updates of work.
SLICE = 1 << 16

#: The scores a HAC records in one pass of a fit's job (FitJob._uncertainty).
RECORD_ROWS = 2048
#: The cost of a recorded score per column, in sample-columns of the fit's passes (the
#: lagged products of each block of lagged.BLOCK rows): 16-25 ns per score-column against
#: 11-13 ns per sample-column of a gradient pass (tracking plants (0, 1), (1, 27), (2, 5),
#: (3, 2))
RECORD_COLUMNS = 3
#: The cost of a long-run covariance (HacCovariance.long_run: prewhitening, bandwidths and
#: the lag window at the last block): 0.4-0.6 ms, whatever the samples
LONG_RUN_COST = 1 << 15
#: The cost per residual of their colour (noise_colour.colour, a spectrum: up to 1 ms for
#: 8192 residuals)
COLOUR_COST = 10

#: A gap-free run of stored samples, normalised: (y, u, weights).
Segment = tuple[np.ndarray, np.ndarray, np.ndarray]


def signal_size(values: np.ndarray) -> float:
    """
    Return a robust size of a centred signal: 1.4826 median |x|, or its RMS if that is 0.

    The median ignores a burst of outliers (which the fits then exclude);
    for Gaussian x it is the standard deviation. 0 for an all-zero or
    non-finite signal. Multiplying x by a power of two multiplies it exactly.
    """
    size = 1.4826 * float(np.median(np.abs(values)))
    if not size > 0.0:
        size = math.sqrt(float(np.mean(values * values)))
    return size if math.isfinite(size) else 0.0


class FitUncertainty(NamedTuple):
    """
    What the recursion takes from a fit beside its estimate, made by the fit's job.

    Attributes
    ----------
    covariance : numpy.ndarray
        P_f, the P to continue with (:meth:`FitResult.covariance`).
    hac : HacCovariance
        The fit's scores recorded (:func:`~.uncertainty.fitted_scores`): the
        recursion's HAC from the fit on.
    root : numpy.ndarray
        R of the fitted initial states (:func:`~.uncertainty.fitted_state_excess`).
    unresolved : numpy.ndarray
        R with the fit's other end where the data do not tell it apart
        (:func:`~.uncertainty.with_unresolved`; ``root`` itself where they do).

    """

    covariance: np.ndarray
    hac: HacCovariance
    root: np.ndarray
    unresolved: np.ndarray


class StoredFit(NamedTuple):
    """
    A fit of the stored samples (see :meth:`SampleStore.start`).

    Attributes
    ----------
    result : FitResult or None
        The fit, None if there was none.
    segments : list of (y, u, weights)
        The normalised segments it fitted.
    scale : numpy.ndarray, shape ``(1 + r,)``
        The scales of y, u_1 ... u_r it chose.
    outliers : int
        The samples it took out as outliers (0 if none).
    uncertainty : FitUncertainty or None
        What the recursion takes from it beside theta; None if it has no
        covariance (:meth:`FitResult.covariance`) or no result.

    """

    result: FitResult | None
    segments: list[Segment]
    scale: np.ndarray
    outliers: int
    uncertainty: FitUncertainty | None = None


class FitJob:
    """
    A fit of the stored samples as they were at one update, done a slice of work at a time.

    :meth:`steps` fits copies of the rows (centred on ``mean``, in the
    scales the rows give), with the outliers it finds marked in its own
    ``breaks`` / ``excluded`` (``break_after``: a break after the last row);
    :meth:`SampleStore.take_marks` copies them into the store. The result
    depends on the job's arrays and numbers only; ``done`` counts the work
    of the passes run (a snapshot keeps it, and a restored job runs the same
    passes again up to it: each pass's cost is known before it runs, so
    ``done`` is always the sum of the first passes' costs).
    """

    def __init__(self, rows: np.ndarray, breaks: np.ndarray, excluded: np.ndarray,
                 mean: np.ndarray | None, scale: np.ndarray, theta: np.ndarray | None,
                 forgetting_factor: float, prior: float, limit: float, position: int,
                 channel: np.ndarray, armax: bool) -> None:
        self.rows, self.breaks, self.excluded = rows, breaks, excluded
        self._marks = (breaks.copy(), excluded.copy())
        self.mean = None if mean is None else np.array(mean, dtype=float)
        self.scale = np.array(scale, dtype=float)
        self.theta = None if theta is None else np.array(theta, dtype=float)
        self.forgetting_factor, self.prior, self.limit = forgetting_factor, prior, limit
        self.position = int(position)
        self.break_after = False
        #: Whether it fits new samples (not a restart's refit of the same: rpem.watch)
        self.fresh = True
        #: Whether its samples follow a plant change (BatchFit.steps: ``after_change``)
        self.after_change = False
        self.done = 0
        self.fitted: StoredFit | None = None
        self._channel, self._armax = channel, armax
        self._steps: Steps | None = None
        #: The cost of the pass announced, to run next
        self._next = 0

    def steps(self, batch: BatchFit) -> Steps:
        """Fit the job's rows with ``batch`` (see :meth:`SampleStore.start`), a pass at a time."""
        rows = self.rows if self.mean is None else self.rows - self.mean
        lam = self.forgetting_factor
        new_scale = SampleStore._scales(rows, self.scale)
        segments = SampleStore._segments(rows, self.breaks, self.excluded, new_scale, lam)
        candidates = []
        if self.theta is not None:
            # theta in the new scales: the b's scale with s_u / s_y
            channel = self._channel
            ratio = (self.scale[channel] / new_scale[channel]) * (new_scale[0] / self.scale[0])
            candidates.append(self.theta * ratio)
        outliers = 0
        with np.errstate(all='ignore'):
            result = yield from batch.steps(segments, candidates, self.prior,
                                            self.after_change)
            if result is not None:
                yield self.rows.shape[0] * batch.loss_columns + PASS_COST
                outliers = self._exclude_outliers(batch, result.theta, segments)
            if outliers:
                segments = SampleStore._segments(rows, self.breaks, self.excluded, new_scale,
                                                 lam)
                result = yield from batch.steps(segments, [result.theta], self.prior,
                                                self.after_change)
            uncertainty = None if result is None else (
                yield from self._uncertainty(result, segments[-1]))
        # the hand-off (SampleStore.advance): the predictor run on over the last segment
        # (with its gradient), the fit installed
        yield segments[-1][0].shape[0] * 2 * (batch.num_parameters + 1) + PASS_COST
        return StoredFit(result, segments, new_scale, outliers, uncertainty)

    def _uncertainty(self, result: FitResult, last: Segment) -> Steps:
        """
        Return the :class:`FitUncertainty` of ``result``, a pass at a time; None if no P_f.

        The work of the hand-off that depends on the fit alone, done before it (the
        HACs' records took 5 and 3 ms of one update on a fit of 8192 samples): the
        fit's scores recorded RECORD_ROWS at a time, the profiled ones too, then R
        (:func:`~.uncertainty.profiled_excess`) and the other end's share
        (:func:`~.uncertainty.with_unresolved`, with the fit's own residuals).
        """
        size, lam = result.information.shape[0], self.forgetting_factor
        yield PASS_COST
        covariance = result.covariance(1.0 / self.prior)
        if covariance is None:
            return None
        hac = yield from _recorded(score_hac(size, lam),
                                   fitted_scores(result.scores, result.profiled[1]))
        information, scores = result.profiled
        profiled = yield from _recorded(score_hac(information.shape[0], lam), scores)
        yield 2 * LONG_RUN_COST  # the held covariance's and the profiled one's
        root = profiled_excess(normalised_covariance(hac, covariance, result.weight, lam),
                               result.information, information, profiled, self.prior,
                               result.weight, lam)
        yield PASS_COST + COLOUR_COST * last[0].shape[0]  # (the colour only where it decides)
        unresolved = with_unresolved(
            root, result.theta, result.alternative, result.weight, lam,
            lambda: result.residuals(last, self._armax),
            result.information + np.eye(size) * self.prior)
        return FitUncertainty(covariance, hac, root, unresolved)

    def advance(self, batch: BatchFit, work: float) -> bool:
        """
        Do the passes that fit in ``work`` (the first whatever its cost); return if it ended.

        :meth:`steps` announces each pass's cost before it runs it: a pass that
        would take the work done over ``work`` waits for the next call, so a
        call does at most ``max(work, one pass)`` (the largest pass: a
        gradient over every stored sample, or the hand-off).
        """
        with np.errstate(all='ignore'):
            if self._steps is None:
                self._steps = self.steps(batch)
                self._next = next(self._steps)  # (steps announces at least the hand-off)
            spent = 0
            while not spent or spent + self._next <= work:
                cost = self._next
                try:
                    self._next = next(self._steps)  # the pass runs; the next is announced
                except StopIteration as end:
                    self.fitted = end.value
                    return True
                finally:
                    self.done += cost
                    spent += cost
        return False

    def state_items(self, channels: int, size: int) -> tuple[dict[str, np.ndarray],
                                                             dict[str, Any]]:
        """Return (arrays, scalars) of the job under ``job_`` names (padded to BATCH_LIMIT)."""
        count = self.breaks.shape[0]
        rows = np.zeros((BATCH_LIMIT, channels))
        rows[:count] = self.rows
        breaks, excluded = np.zeros(BATCH_LIMIT, dtype=bool), np.zeros(BATCH_LIMIT, dtype=bool)
        # the marks as the job started (its passes mark them again when it runs anew)
        breaks[:count], excluded[:count] = self._marks
        arrays = {'job_rows': rows, 'job_breaks': breaks, 'job_excluded': excluded,
                  'job_mean': np.zeros(channels) if self.mean is None else self.mean,
                  'job_scale': self.scale,
                  'job_theta': np.zeros(size) if self.theta is None else self.theta}
        scalars = {'job_count': count, 'job_done': self.done, 'job_fresh': self.fresh,
                   'job_after_change': self.after_change,
                   'job_ended': self.fitted is not None,
                   'job_position': self.position, 'job_has_mean': self.mean is not None,
                   'job_has_theta': self.theta is not None,
                   'job_forgetting_factor': self.forgetting_factor, 'job_prior': self.prior,
                   'job_limit': self.limit}
        return arrays, scalars

    @staticmethod
    def empty_items(channels: int, size: int) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return the ``job_`` state of no job (job_count 0)."""
        arrays = {'job_rows': np.zeros((BATCH_LIMIT, channels)),
                  'job_breaks': np.zeros(BATCH_LIMIT, dtype=bool),
                  'job_excluded': np.zeros(BATCH_LIMIT, dtype=bool),
                  'job_mean': np.zeros(channels), 'job_scale': np.ones(channels),
                  'job_theta': np.zeros(size)}
        scalars = {'job_count': 0, 'job_done': 0, 'job_fresh': True, 'job_ended': False,
                   'job_after_change': False,
                   'job_position': 0,
                   'job_has_mean': False,
                   'job_has_theta': False, 'job_forgetting_factor': 1.0, 'job_prior': 0.0,
                   'job_limit': 0.0}
        return arrays, scalars

    @classmethod
    def from_state(cls, arrays: dict[str, np.ndarray], scalars: dict[str, Any],
                   channel: np.ndarray, armax: bool, batch: BatchFit) -> FitJob | None:
        """Return the job of a :meth:`state_items` snapshot, run again to its work done."""
        count = int(scalars.get('job_count', 0))
        if not count:
            return None
        job = cls(np.array(arrays['job_rows'][:count], dtype=float),
                  np.array(arrays['job_breaks'][:count], dtype=bool),
                  np.array(arrays['job_excluded'][:count], dtype=bool),
                  arrays['job_mean'] if scalars['job_has_mean'] else None, arrays['job_scale'],
                  arrays['job_theta'] if scalars['job_has_theta'] else None,
                  float(scalars['job_forgetting_factor']), float(scalars['job_prior']),
                  float(scalars['job_limit']), int(scalars['job_position']), channel, armax)
        job.fresh = bool(scalars['job_fresh'])
        # (a snapshot from before it: the comparison of the ends as it was)
        job.after_change = bool(scalars.get('job_after_change', False))
        done = int(scalars['job_done'])
        while job.done < done:  # the same passes, to the same point
            job.advance(batch, done - job.done)
        if scalars['job_ended']:
            job.advance(batch, math.inf)
        return job

    def _exclude_outliers(self, batch: BatchFit, theta: np.ndarray,
                          segments: list[Segment]) -> int:
        """
        Take the samples that the gate would refuse at theta out of the fits; return how many.

        OE: each such sample weighs 0 from then on (its output enters nothing
        else); ARMAX: it becomes a segment of its own (a break before and
        after it: its output is a lag of the next ones). Marked in the job's
        ``breaks`` / ``excluded`` (and by :meth:`SampleStore.take_marks` in
        the store, so that no fit uses it again); 0 if there are none or more
        than OUTLIER_SHARE of the samples (then it is the model, not outliers).
        """
        bad = batch.outliers(theta, segments, self.limit)
        count = self.breaks.shape[0]
        if not 0 < bad.shape[0] <= OUTLIER_SHARE * count:
            return 0
        for row in bad:
            if not self._armax:
                self.excluded[row] = True
                continue
            self.breaks[row] = True
            if row + 1 < count:
                self.breaks[row + 1] = True
            else:
                self.break_after = True
        return bad.shape[0]


def _recorded(hac: HacCovariance, scores: np.ndarray) -> Steps:
    """
    Record ``scores`` in ``hac`` RECORD_ROWS at a time, a pass each, all in its estimate.

    The rows short of a last whole block complete it (HacCovariance.complete): a fit of
    fewer than lagged.BLOCK samples left the HAC no estimate, and rpem no std until the
    first block of the recursion's scores after a fit of a block or more (312-389
    samples into tracking runs, valid from 120-160 on: docs/trust.md, "Precision at all
    times"). Return ``hac``.
    """
    for start in range(0, scores.shape[0], RECORD_ROWS):
        chunk = scores[start:start + RECORD_ROWS]
        yield chunk.size * RECORD_COLUMNS + PASS_COST
        hac.record_all(chunk)  # (in pieces: the same sums, bit for bit: LaggedProducts.extend)
    hac.complete()  # (its cost is in the last chunk's)
    return hac


class SampleStore:
    """
    The last ``BATCH_LIMIT`` samples, their segment breaks and exclusions, and the fit schedule.

    Parameters
    ----------
    order, num_inputs, feedthrough, input_delay, armax, offset
        The model structure, as for :class:`~bcid_ros.estimators.rpem.fit.BatchFit`.
    channel : numpy.ndarray of int, shape ``(p,)``
        The signal channel (0 = y, i = u_i) of each parameter.

    Attributes
    ----------
    break_pending : bool
        Whether the next stored sample starts a segment.

    """

    def __init__(self, order: int, num_inputs: int, feedthrough: bool,
                 input_delay: tuple[int, ...], armax: bool, offset: bool,
                 channel: np.ndarray) -> None:
        self._structure = (order, num_inputs, feedthrough, input_delay, armax, offset)
        self._channels = 1 + num_inputs
        self._armax = armax
        self._channel = channel
        self.first_fit = max(FIRST_FIT_SAMPLES, FIRST_FIT_PER_PARAMETER * channel.shape[0])
        self._batch: BatchFit | None = None
        self.clear()

    def clear(self) -> None:
        """Forget every sample and start the schedule again."""
        self.buffer = np.zeros((BATCH_LIMIT, self._channels))
        self.breaks = np.zeros(BATCH_LIMIT, dtype=bool)
        self.excluded = np.zeros(BATCH_LIMIT, dtype=bool)
        self.position = 0
        self.stored = 0
        self.since_start = 0
        self.next_fit = self.first_fit
        self.break_pending = False
        #: The fit on its way (spread over the updates), or None
        self.job: FitJob | None = None

    def add(self, y: float, u: np.ndarray, mean: np.ndarray | None,
            excluded: bool = False) -> bool:
        """
        Keep a sample on the raw operating point; return whether a fit is due now.

        ``mean`` is the running mean ``[y, u_1 ... u_r]`` the sample was
        centred on (None without ``detrend: mean``): a fit centres on the
        means of its own time. An ``excluded`` sample (OE: its output
        refused) keeps its input in the simulation and weighs 0 in the fits.
        """
        position = self.position
        row = self.buffer[position]
        if mean is None:
            row[0] = y
            row[1:] = u
        else:  # undo the running centring
            row[0] = y + mean[0]
            row[1:] = u + mean[1:]
        self.breaks[position] = self.break_pending
        self.excluded[position] = excluded
        self.break_pending = False
        self.position = (position + 1) % BATCH_LIMIT
        self.stored = min(self.stored + 1, BATCH_LIMIT)
        self.since_start += 1
        return self.since_start == self.next_fit

    def restart_schedule(self, keep: int = 0) -> bool:
        """
        Keep only the last ``keep`` samples for the fits (a plant change at that point).

        The samples before the change point are of the old plant: no fit may
        blend them in. The kept ones weigh again where they were excluded
        (OE: an output refused against the old plant). The schedule starts
        again from them; returns whether they are already enough for a fit
        (the caller then fits now). With ``keep`` 0 the next stored sample
        starts a segment.
        """
        keep = min(max(int(keep), 0), self.stored)
        self.job = None  # a fit on its way blends the old plant in
        self.stored = keep
        self.since_start = keep
        self.next_fit = max(self.first_fit, keep)
        if keep:
            kept = np.arange(self.position - keep, self.position) % BATCH_LIMIT
            self.breaks[kept[0]] = True
            # the outputs the gate (or a fit's outlier test) refused among them were judged
            # against the old plant: the first errors of the new one are large, not wrong.
            # They weigh again; the new plant's fits take out its own outliers
            self.excluded[kept] = False
        else:
            self.break_pending = True
        return keep >= self.first_fit

    def refused_run(self) -> int:
        """Count the newest stored samples that weigh 0 in a row (the gate's last refusals)."""
        index = (self.position - 1 - np.arange(self.stored)) % BATCH_LIMIT
        weighed = np.flatnonzero(~self.excluded[index])
        return int(weighed[0]) if weighed.size else self.stored

    # ------------------------------------------------------------- the fit
    def start(self, mean: np.ndarray | None, scale: np.ndarray, theta: np.ndarray | None,
              forgetting_factor: float, prior: float, limit: float, fresh: bool,
              after_change: bool = False) -> None:
        """
        Start a fit of the stored samples, spread over the next updates; schedule the next.

        The job replaces any fit on its way (:meth:`advance` does its work).

        Parameters
        ----------
        mean : numpy.ndarray or None, shape ``(1 + r,)``
            The current means to centre on (None without ``detrend: mean``).
        scale : numpy.ndarray, shape ``(1 + r,)``
            The scales now, kept for a channel without a size.
        theta : numpy.ndarray or None, shape ``(p,)``
            The current estimate in the units of ``scale``, a candidate start
            (None before the first fit).
        forgetting_factor : float
            lambda of the weights.
        prior : float
            1 / p0, the information added to the fit's diagonal.
        limit : float
            The gate's limit of a prediction error, in robust scales.
        fresh : bool
            Whether it fits new samples (not a restart's refit of the same ones).
        after_change : bool
            Whether the samples follow a plant change (their first segment starts
            where the old plant left the output: :meth:`BatchFit.steps`).

        """
        self.next_fit = self._after(self.since_start, forgetting_factor)
        rows, breaks, excluded = self._rows()
        self.job = FitJob(rows, breaks, excluded, mean, scale, theta, forgetting_factor, prior,
                          limit, self.position, self._channel, self._armax)
        self.job.fresh = fresh
        self.job.after_change = after_change

    def advance(self) -> tuple[StoredFit, bool] | None:
        """
        Do a SLICE of the fit on its way; if it ended, return it and whether it was fresh.

        The fit is returned with its predictor run on over the samples stored
        now (:meth:`BatchFit.continued`), its outliers marked in the store.
        """
        job = self.job
        if job is None or not job.advance(self.fitter(), SLICE):
            return None
        self.job = None
        self.take_marks(job)
        fitted = job.fitted
        rows, breaks, excluded = self._rows()
        if job.mean is not None:
            rows = rows - job.mean
        segments = self._segments(rows, breaks, excluded, fitted.scale, job.forgetting_factor)
        result = None if fitted.result is None else self.fitter().continued(fitted.result,
                                                                            segments)
        return StoredFit(result, segments, fitted.scale, fitted.outliers,
                         fitted.uncertainty), job.fresh

    def take_marks(self, job: FitJob) -> None:
        """Mark the outliers ``job`` found in the store (those of its rows still stored)."""
        count = job.breaks.shape[0]
        # ring slot of job row k: job.position - count + k; overwritten since, the oldest
        written = (self.position - job.position) % BATCH_LIMIT
        first = max(written - (BATCH_LIMIT - count), 0)
        index = (np.arange(first, count) + job.position - count) % BATCH_LIMIT
        self.breaks[index] |= job.breaks[first:]
        self.excluded[index] |= job.excluded[first:]
        if job.break_after and written == 0:
            self.break_pending = True

    def fitter(self) -> BatchFit:
        """Return the batch fit of the structure (made once)."""
        if self._batch is None:
            self._batch = BatchFit(*self._structure)
        return self._batch

    @staticmethod
    def _after(since_start: int, forgetting_factor: float) -> int:
        """
        Return the sample count of the next fit after one at ``since_start`` (0: none).

        The count grows by FIT_GROWTH up to BATCH_LIMIT. Beyond it, with
        forgetting, a fit of the last BATCH_LIMIT samples every SLIDE samples
        (a sliding schedule: the weights lambda^(T-t) of that window are the
        recursion's own memory up to lambda^BATCH_LIMIT); without forgetting
        the recursion carries on from the fits of the samples since the last
        change (the change detector restarts the schedule), since a fit of
        the last BATCH_LIMIT samples alone would forget the older ones the
        recursion still weighs fully.
        """
        later = math.ceil(FIT_GROWTH * since_start)
        if later <= BATCH_LIMIT:
            return later
        return since_start + SLIDE if forgetting_factor < 1.0 else 0

    def _rows(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the stored samples, their segment starts and exclusions, oldest first."""
        # the ring positions of the last `stored` samples (they wrap round the ring's end
        # when a plant change restarted the count part of the way through it)
        index = np.arange(self.position - self.stored, self.position) % BATCH_LIMIT
        return self.buffer[index], self.breaks[index], self.excluded[index]

    @staticmethod
    def _scales(rows: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """Return per channel the power of two at or above its robust size (else ``scale``)."""
        sizes = np.array([signal_size(rows[:, channel]) for channel in range(rows.shape[1])])
        return np.where(sizes > 0.0, rules.powers_of_two_at_least(sizes), scale)

    @staticmethod
    def _segments(rows: np.ndarray, breaks: np.ndarray, excluded: np.ndarray,
                  scale: np.ndarray, forgetting_factor: float) -> list[Segment]:
        """Split the normalised rows into gap-free segments (y, u, weights)."""
        lam = forgetting_factor
        count = rows.shape[0]
        # sample t of T weighs lambda^(T-1-t), an excluded one 0
        weights = lam ** np.arange(count - 1, -1, -1, dtype=float) if lam < 1.0 else np.ones(
            count)
        weights[excluded] = 0.0
        normalised = rows / scale
        starts = [0] + [int(k) for k in np.flatnonzero(breaks) if k > 0] + [count]
        return [(normalised[a:b, 0], normalised[a:b, 1:], weights[a:b])
                for a, b in zip(starts[:-1], starts[1:]) if b > a]

    # ------------------------------------------------------------ the state
    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the store under the estimator's state names."""
        arrays = {'buffer': self.buffer, 'breaks': self.breaks, 'excluded': self.excluded}
        scalars = {'buffer_position': self.position, 'stored': self.stored,
                   'since_start': self.since_start, 'next_fit': self.next_fit,
                   'break_pending': self.break_pending}
        size = self._channel.shape[0]
        job_arrays, job_scalars = (FitJob.empty_items(self._channels, size) if self.job is None
                                   else self.job.state_items(self._channels, size))
        return {**arrays, **job_arrays}, {**scalars, **job_scalars}

    def with_job_items(self, arrays: dict[str, np.ndarray],
                       scalars: dict[str, Any]) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return a snapshot's arrays and scalars with those of no job where it has none."""
        empty_arrays, empty_scalars = FitJob.empty_items(self._channels, self._channel.shape[0])
        return {**empty_arrays, **arrays}, {**empty_scalars, **scalars}

    def load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made (the arrays are not copied)."""
        self.buffer, self.breaks, self.excluded = (arrays['buffer'], arrays['breaks'],
                                                   arrays['excluded'])
        self.position = int(scalars['buffer_position'])
        self.stored = int(scalars['stored'])
        self.since_start = int(scalars['since_start'])
        self.next_fit = int(scalars['next_fit'])
        self.break_pending = bool(scalars['break_pending'])
        # the fit that was on its way runs its passes again, to the work it had done
        self.job = FitJob.from_state(arrays, scalars, self._channel, self._armax, self.fitter())
