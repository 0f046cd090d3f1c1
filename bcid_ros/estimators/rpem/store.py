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
:meth:`SampleStore.fit` fits them with
:class:`~bcid_ros.estimators.rpem.fit.BatchFit` (Ljung, *System
Identification*, 2nd ed., 1999, ch. 10): centred on the current means, in
the units of one power of two per channel at or above its robust size
(:func:`signal_size`, :func:`~bcid_ros.estimators.rules.powers_of_two_at_least`),
sample t of T weighing :math:`\lambda^{T-1-t}`; the samples the fit's
prediction errors mark as outliers are then taken out and the fit repeated.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from bcid_ros.estimators import rules
from bcid_ros.estimators.rpem.fit import BatchFit, FitResult

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


class StoredFit(NamedTuple):
    """
    A fit of the stored samples (see :meth:`SampleStore.fit`).

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

    """

    result: FitResult | None
    segments: list[Segment]
    scale: np.ndarray
    outliers: int


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
        blend them in. The schedule starts again from the kept ones; returns
        whether they are already enough for a fit (the caller then fits now).
        With ``keep`` 0 the next stored sample starts a segment.
        """
        keep = min(max(int(keep), 0), self.stored)
        self.stored = keep
        self.since_start = keep
        self.next_fit = max(self.first_fit, keep)
        if keep:
            self.breaks[(self.position - keep) % BATCH_LIMIT] = True
        else:
            self.break_pending = True
        return keep >= self.first_fit

    # ------------------------------------------------------------- the fit
    def fit(self, mean: np.ndarray | None, scale: np.ndarray, theta: np.ndarray | None,
            forgetting_factor: float, prior: float, limit: float) -> StoredFit:
        """
        Fit the stored samples and schedule the next fit.

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

        Returns
        -------
        StoredFit

        """
        self.next_fit = self._after(self.since_start, forgetting_factor)
        rows, breaks, excluded = self._rows()
        if mean is not None:
            rows = rows - mean
        new_scale = self._scales(rows, scale)
        segments = self._segments(rows, breaks, excluded, new_scale, forgetting_factor)
        if self._batch is None:
            self._batch = BatchFit(*self._structure)
        candidates = []
        if theta is not None:
            # theta in the new scales: the b's scale with s_u / s_y
            channel = self._channel
            ratio = (scale[channel] / new_scale[channel]) * (new_scale[0] / scale[0])
            candidates.append(theta * ratio)
        outliers = 0
        with np.errstate(all='ignore'):
            result = self._batch.fit(segments, candidates, prior)
            if result is not None:
                outliers = self._exclude_outliers(result.theta, segments, breaks, excluded,
                                                  limit)
            if outliers:
                segments = self._segments(rows, breaks, excluded, new_scale, forgetting_factor)
                result = self._batch.fit(segments, [result.theta], prior)
        return StoredFit(result, segments, new_scale, outliers)

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

    def _exclude_outliers(self, theta: np.ndarray, segments: list[Segment], breaks: np.ndarray,
                          excluded: np.ndarray, limit: float) -> int:
        """
        Take the samples that the gate would refuse at theta out of the fits; return how many.

        OE: each such sample weighs 0 from then on (its output enters nothing
        else); ARMAX: it becomes a segment of its own (a break before and
        after it: its output is a lag of the next ones). Marked in
        ``breaks`` / ``excluded`` and in the store, so that no fit uses it
        again; 0 if there are none or more than OUTLIER_SHARE of the samples
        (then it is the model, not outliers).
        """
        bad = self._batch.outliers(theta, segments, limit)
        count = breaks.shape[0]
        if not 0 < bad.shape[0] <= OUTLIER_SHARE * count:
            return 0
        first = self.position - count
        for row in bad:
            if not self._armax:
                excluded[row] = True
                self.excluded[(first + row) % BATCH_LIMIT] = True
                continue
            breaks[row] = True
            self.breaks[(first + row) % BATCH_LIMIT] = True
            if row + 1 < count:
                breaks[row + 1] = True
                self.breaks[(first + row + 1) % BATCH_LIMIT] = True
            else:
                self.break_pending = True
        return bad.shape[0]

    # ------------------------------------------------------------ the state
    def state_items(self) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        """Return (arrays, scalars) of the store under the estimator's state names."""
        arrays = {'buffer': self.buffer, 'breaks': self.breaks, 'excluded': self.excluded}
        scalars = {'buffer_position': self.position, 'stored': self.stored,
                   'since_start': self.since_start, 'next_fit': self.next_fit,
                   'break_pending': self.break_pending}
        return arrays, scalars

    def load_state(self, arrays: dict[str, np.ndarray], scalars: dict[str, Any]) -> None:
        """Take over what :meth:`state_items` made (the arrays are not copied)."""
        self.buffer, self.breaks, self.excluded = (arrays['buffer'], arrays['breaks'],
                                                   arrays['excluded'])
        self.position = int(scalars['buffer_position'])
        self.stored = int(scalars['stored'])
        self.since_start = int(scalars['since_start'])
        self.next_fit = int(scalars['next_fit'])
        self.break_pending = bool(scalars['break_pending'])
