r"""
The sequential test for a plant change: CUSUMs on the whitened one-step errors.

An estimator of a plant that has changed predicts with the old model, so its
one-step errors grow: e(t) = v(t) + (G_new - G_old) u(t) has a larger variance
and, with an input or a load off zero, a shifted mean. :class:`ChangeDetector`
accumulates that evidence sample by sample with Page's CUSUM (Page 1954;
Basseville and Nikiforov, *Detection of Abrupt Changes*, 1993, sec. 2.2),
so that a large change is seen within a few samples and a small persistent
one once its evidence has added up.

**The errors.** Each plant gives its normalised one-step error (rls and
bcrls: the a-priori error over the square root of the gain term, e/sqrt(s);
rpem: the one-step error of its last fit's model, whose residuals prime the
reference, :meth:`ChangeDetector.prime`).
The detector keeps a reference of them with memory ``memory`` (weights
mu^(T-t), mu = 1 - 1/memory): the autocovariances R_0, R_1, R_2 of e - m, with
m their mean over about ``MEAN_MEMORY`` samples (an estimator's errors carry
a slowly moving offset that is no change of the plant). From these,
Levinson-Durbin gives the AR(2) predictor of the error's own colour,
x(t) = (e(t) - m) - f_1 (e(t-1) - m) - f_2 (e(t-2) - m), with variance v_2,
and the test statistic is z(t) = x(t)/sqrt(v_2): N(0, 1) and white as long
as the reference describes the errors (coloured errors, as an output-error
model's under coloured noise, would otherwise make the CUSUM's sums far
more variable than its design). The filter is
recomputed every ``BLOCK`` samples; each sample is tested before it joins
the reference.

**The CUSUM** is the log-likelihood ratio of a variance ``VARIANCE_RATIO`` times
the reference's against it (z ~ N(0, rho) against N(0, 1)), with z clipped at
``CLIP`` standard deviations so that one spike adds at most a fifth of the
threshold (a clipped increment only lowers the statistic, so the bound
below still holds):

.. math::

    S \leftarrow \max\big(0,\ S + \tfrac12(1 - 1/\rho) z^2 - \tfrac12\ln\rho\big)

A change is detected when S reaches h; the change point is then placed
within the run since S was last 0 (:func:`change_age`).

**Why the variance alone.** After a change the error is v + (G_new - G_old) u:
the input-driven part adds variance whatever the input, and a mean only with
an input off zero. Two mean CUSUMs (shifts of +-0.5 sigma) were built and
measured: on 60 stationary plants of the realistic family they raised 14 of
14 false detections of rls and 18 of 18 of rpem, because the estimators'
errors carry a slowly moving offset (the operating point's means converging,
the slowest colour of the noise, which an AR(2) does not whiten). The errors
are therefore centred on their mean over ``MEAN_MEMORY`` samples, and a
shift of the mean shows only while that mean catches up: as an excess
z^2 of about d^2 over some 50 samples, enough for a step of 1.5 sigma or more.

**The threshold from the false-alarm rate.** For a CUSUM of log-likelihood
ratios, exp(S) restarted at every zero is a non-negative supermartingale
under the null, so the mean run length to a false alarm is at least e^h
(Lorden 1971; Basseville and Nikiforov, eq. 5.2.49): h = ln(1/``false_alarm``)
= 11.51 for the stated rate of 1 per 100,000 samples. The bound holds for
errors that the reference describes (Gaussian, AR(2)-coloured, variance
known); heavier tails or a reference learnt on fewer samples raise the
rate. The measured rates are in docs/tracking.md.

**Detection delay** is about h over the mean increment under the change,
0.1 z^2 - 0.112 for an error variance z^2 times the reference's (measured
medians: 9 samples for 25 times, the clip; 59 for 3 times, 125 for 2 times,
299 for 1.5 times). The design ratio 1.25 is small on purpose: the false
alarms of the estimators' errors come from bursts of large errors, which a
larger design weighs more (on 60 stationary realistic plants rpem had 9.05
false detections per 1e5 samples at 2, 3.83 at 1.5, 0.70 at 1.25).

Everything is held over a leading plant axis (K plants; ``plants=None`` for
one, whose per-sample step runs on Python floats and gives the same bits).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

#: The stated false-alarm rate: detections per sample of a plant that does not change.
FALSE_ALARM = 1e-5
#: The variance ratio the variance CUSUM is designed for.
VARIANCE_RATIO = 1.25
#: A sample's z is clipped at this many standard deviations (a spike adds at most 2.4).
CLIP = 5.0
#: The reference's memory (samples), and the effective samples it needs before any test.
MEMORY = 2000
#: See MEMORY.
WARMUP = 500
#: The errors are centred on their mean over about this many samples: an estimator's
#: errors carry a slowly moving offset (its operating point's means converging, the
#: slowest colour of the noise) that is no change of the plant.
MEAN_MEMORY = 100
#: The whitening filter is recomputed every this many samples.
BLOCK = 64
#: Largest reflection coefficient of the whitening filter.
MAX_REFLECTION = 0.995
#: The last RING statistics z are kept, to place the change point (:func:`change_age`).
RING = 1024

#: The increments' constants.
_VAR_GAIN = 0.5 * (1.0 - 1.0 / VARIANCE_RATIO)
_VAR_COST = 0.5 * math.log(VARIANCE_RATIO)
_CLIP2 = CLIP * CLIP


def threshold(false_alarm: float = FALSE_ALARM) -> float:
    """Return h = ln(1 / false_alarm), from Lorden's bound: run length to a false alarm >= e^h."""
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f'false_alarm must be in (0, 1), got {false_alarm!r}')
    return math.log(1.0 / false_alarm)


def change_age(run: np.ndarray) -> int:
    r"""
    Return how many of the last samples belong to the new regime, from the detecting run.

    The CUSUM's last zero is the change time of its design alternative;
    a large change makes a few samples before it count too (each null sample
    adds little against a small design). Over the detecting run ``run`` (the
    statistics z since that zero, oldest first), the change time is
    re-estimated by the generalised likelihood ratio with the new variance
    estimated from the samples after each candidate (Basseville and
    Nikiforov, sec. 2.4.3):

    .. math::

        k^* = \arg\max_k\ \tfrac12 n_k\,(v_k - 1 - \ln v_k)

    with :math:`n_k` the samples from k on and :math:`v_k` their mean of
    :math:`z^2`. Returns :math:`n_{k^*}` (>= 1).
    """
    count = run.shape[0]
    if count <= 1:
        return max(count, 1)
    n = np.arange(count, 0, -1, dtype=float)
    v = np.cumsum((run * run)[::-1])[::-1] / n
    score = np.where(v > 1.0, 0.5 * n * (v - 1.0 - np.log(np.maximum(v, 1.0))), 0.0)
    return int(n[int(np.argmax(score))])


@dataclasses.dataclass
class DetectorState:
    """
    The arrays of a :class:`ChangeDetector`, each ``(K,)`` (see its docstring).

    All but the ring are the rows of one block, in this order (r0-r2 and the
    two lags next to each other: a record updates each group in one operation).
    """

    weight: np.ndarray
    mean: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    r2: np.ndarray
    lag1: np.ndarray
    lag2: np.ndarray
    f1: np.ndarray
    f2: np.ndarray
    inverse_std: np.ndarray
    statistic: np.ndarray
    run: np.ndarray
    seen: np.ndarray
    armed: np.ndarray
    mean_weight: np.ndarray
    ring: np.ndarray


#: The row of each of DetectorState's per-plant numbers in the detector's block.
_ROW = {field.name: row for row, field in enumerate(dataclasses.fields(DetectorState))}
#: The rows of R_0, R_1, R_2 and of the two lags (each group adjacent, see DetectorState).
_CORRELATIONS = slice(_ROW['r0'], _ROW['r2'] + 1)
_LAGS = slice(_ROW['lag1'], _ROW['lag2'] + 1)


class ChangeDetector:
    """
    The CUSUM of the whitened normalised errors of K plants (see the module docstring).

    Parameters
    ----------
    plants : int or None
        K plants, or None for one (the state's arrays then have one row and
        :meth:`record` takes and returns floats).
    false_alarm : float
        The stated false-alarm rate per sample, in (0, 1).
    memory : float
        The reference's memory in samples, >= 100.

    Attributes
    ----------
    threshold : float
        h of the CUSUM.
    state : DetectorState
        The per-plant arrays.

    """

    def __init__(self, plants: int | None = None, false_alarm: float = FALSE_ALARM,
                 memory: float = MEMORY) -> None:
        self.plants = plants
        self.threshold = threshold(false_alarm)
        if not memory >= 100:
            raise ValueError(f'memory must be >= 100 samples, got {memory!r}')
        self._mu = 1.0 - 1.0 / memory
        self._mu_mean = 1.0 - 1.0 / MEAN_MEMORY
        count = 1 if plants is None else int(plants)
        fields = len(dataclasses.fields(DetectorState))
        # the per-plant numbers as the rows of one block (F, K), each field a view of its
        # row: a record reads and writes them in one operation, not one per field
        self._values = np.zeros((fields - 1, count))
        self._all = np.arange(count)
        self._lagged = np.empty((3, count))
        self._state = DetectorState(*self._values, np.zeros((count, RING)))
        # one plant: its numbers as Python floats between records (None: the block holds them)
        self._one: list[float] | None = None
        self.clear()

    @property
    def state(self) -> DetectorState:
        """Return the per-plant arrays (one plant's numbers written back first)."""
        self._write_back()
        return self._state

    def _write_back(self) -> None:
        """Put one plant's numbers, held as Python floats since its last record, in the block."""
        if self._one is not None:
            self._values[:, 0] = self._one
            self._one = None

    # ------------------------------------------------------------- the API
    def clear(self, rows: Any = slice(None)) -> None:
        """Start plants ``rows`` afresh: no reference, no evidence (after a restart)."""
        for field in dataclasses.fields(DetectorState):
            getattr(self.state, field.name)[rows] = 0.0

    def prime(self, residuals: np.ndarray, row: int = 0) -> None:
        """
        Start plant ``row`` afresh with the reference of ``residuals`` (oldest first).

        For an estimator that has just been refitted: the residuals of the fit
        at its new estimate are the reference its next errors are judged
        against (the errors of the model before the fit, of another size and
        colour, would be none). The same weights as :meth:`record` (the
        newest weighs 1, the one k samples older mu^k) and the same centring on
        the final mean; armed at once with WARMUP of them or more, otherwise
        the following samples complete the reference.
        """
        st = self.state
        self.clear(row)
        x = np.asarray(residuals, dtype=float)[-RING:]
        count = x.shape[0]
        if not count:
            return
        ages = np.arange(count - 1, -1, -1, dtype=float)
        weights = self._mu ** ages
        mean_weights = self._mu_mean ** ages
        mean_weight = float(mean_weights.sum())
        mean = float(mean_weights.dot(x)) / mean_weight
        x = x - mean
        st.weight[row], st.mean[row] = float(weights.sum()), mean
        st.mean_weight[row] = mean_weight
        st.r0[row] = float(weights.dot(x * x))
        st.r1[row] = float(weights[1:].dot(x[1:] * x[:-1]))
        st.r2[row] = float(weights[2:].dot(x[2:] * x[:-2]))
        st.lag1[row] = x[-1]
        st.lag2[row] = x[-2] if count > 1 else 0.0
        st.seen[row] = float(count)
        if count >= WARMUP:
            self._whiten(np.array([row], dtype=np.intp))

    def record(self, error: Any) -> Any:
        """
        Test and learn one normalised error of every plant; return where a change is detected.

        One plant (``plants=None``): ``error`` a float, returns the number of
        samples since the estimated change point (the age of the new regime,
        >= 1, this sample included) or 0 when nothing is detected. K plants:
        ``error`` ``(K,)``, returns ``(K,)`` ages (int), 0 where nothing is.
        A plant whose change is detected starts afresh (:meth:`clear`).
        """
        if self.plants is None:
            return self._record_one(float(error))
        return self.record_rows(np.arange(self.state.weight.shape[0]), np.asarray(error))

    def record_rows(self, rows: np.ndarray, error: np.ndarray) -> np.ndarray:
        """Record ``error`` ``(R,)`` of plants ``rows`` (indices); return their ages (int)."""
        rows = np.asarray(rows, dtype=np.intp)
        error = np.asarray(error, dtype=float)
        self._write_back()
        values = self._values
        # every plant in order (the common case): the fields' own rows, in place
        every = rows.shape[0] == values.shape[1] and bool((rows == self._all).all())
        block = values if every else values[:, rows]
        (weight, mean, _, _, _, lag1, lag2, f1, f2, inverse_std, statistic, run, seen,
         armed, mean_weight) = block
        age = np.zeros(rows.shape[0], dtype=np.int64)
        x = error - mean
        tested = armed > 0.0
        if tested.all():
            z = (x - f1 * lag1 - f2 * lag2) * inverse_std
            detected = self._test(rows, z, seen, statistic, run, age)
        elif tested.any():
            # z of every row (element-wise: the same numbers), then those of the armed ones
            tested = np.flatnonzero(tested)
            z = ((x - f1 * lag1 - f2 * lag2) * inverse_std)[tested]
            kept, lengths = statistic[tested], run[tested]
            found = np.zeros(z.shape[0], dtype=np.int64)
            detected = self._test(rows[tested], z, seen[tested], kept, lengths, found)
            statistic[tested], run[tested], age[tested] = kept, lengths, found
        else:
            detected = False
        self._learn(block, x)
        if not every:
            values[:, rows] = block
        whole = np.fmod(seen, BLOCK) == 0.0
        if whole.any():
            due = whole & (seen >= WARMUP)
            if due.any():
                self._whiten(rows[due])
        if detected:
            self.clear(rows[age > 0])
        return age

    def _test(self, rows: np.ndarray, z: np.ndarray, seen: np.ndarray, statistic: np.ndarray,
              run: np.ndarray, age: np.ndarray) -> bool:
        """Clip z, keep it in the ring, step the CUSUMs of ``rows`` in place; return any found."""
        np.maximum(z, -CLIP, out=z)
        np.minimum(z, CLIP, out=z)
        self._state.ring[rows, seen.astype(np.intp) % RING] = z
        value = statistic + (_VAR_GAIN * (z * z) - _VAR_COST)
        positive = value > 0.0
        statistic[:] = np.where(positive, value, 0.0)
        # run + 1 where the sum is positive, 0 elsewhere (the run is finite and >= 0)
        run += 1.0
        run *= positive
        detected = np.flatnonzero(statistic >= self.threshold)
        for k in detected.tolist():
            age[k] = change_age(self._run(int(rows[k]), int(run[k])))
        return detected.size > 0

    def _learn(self, block: np.ndarray, x: np.ndarray) -> None:
        """Add the samples x to the reference held in ``block`` (the fields' rows), in place."""
        weight, mean = block[_ROW['weight']], block[_ROW['mean']]
        mean_weight, seen = block[_ROW['mean_weight']], block[_ROW['seen']]
        weight *= self._mu
        weight += 1.0
        mean_weight *= self._mu_mean
        mean_weight += 1.0
        mean += x / mean_weight
        # r_k = mu r_k + x x(t-k), k = 0, 1, 2, on the rows [x; lag1; lag2]; then the lags move
        lagged = self._lagged if block is self._values else np.empty((3, x.shape[0]))
        lagged[0] = x
        lagged[1:] = block[_LAGS]
        correlations = block[_CORRELATIONS]
        correlations *= self._mu
        correlations += x * lagged
        block[_LAGS] = lagged[:2]
        seen += 1.0

    def _run(self, row: int, length: int) -> np.ndarray:
        """Return plant ``row``'s last ``length`` statistics z (at most RING), oldest first."""
        st = self.state
        end = int(st.seen[row]) + 1
        index = np.arange(end - min(length, RING), end) % RING
        return st.ring[row, index]

    def _whiten(self, rows: np.ndarray) -> None:
        """Fit the AR(2) predictor of the errors' colour (Levinson-Durbin) and arm ``rows``."""
        st = self.state
        r0, r1, r2 = st.r0[rows], st.r1[rows], st.r2[rows]
        usable = r0 > 0.0
        safe = np.where(usable, r0, 1.0)
        k1 = np.clip(r1 / safe, -MAX_REFLECTION, MAX_REFLECTION)
        v1 = safe * (1.0 - k1 * k1)
        k2 = np.clip((r2 - k1 * r1) / v1, -MAX_REFLECTION, MAX_REFLECTION)
        v2 = v1 * (1.0 - k2 * k2) / np.maximum(st.weight[rows], 1.0)
        st.f1[rows] = k1 * (1.0 - k2)
        st.f2[rows] = k2
        st.inverse_std[rows] = np.where(usable & (v2 > 0.0), 1.0 / np.sqrt(
            np.where(v2 > 0.0, v2, 1.0)), 0.0)
        st.armed[rows] = np.where(usable, 1.0, 0.0)

    def _record_one(self, error: float) -> int:
        """
        :meth:`record_rows` of one plant on Python floats (the same operations, same bits).

        Its numbers stay Python floats from one record to the next (``_one``); reading
        :attr:`state` writes them back (a read and a write of the block each sample were
        half of a record's time).
        """
        one = self._one
        (weight, mean, r0, r1, r2, lag1, lag2, f1, f2, inverse_std, statistic, run, seen,
         armed, mean_weight) = self._values[:, 0].tolist() if one is None else one
        x = error - mean
        age = 0
        if armed:
            z = (x - f1 * lag1 - f2 * lag2) * inverse_std
            z = -CLIP if z < -CLIP else (CLIP if z > CLIP else z)
            self._state.ring[0, int(seen) % RING] = z
            statistic += _VAR_GAIN * (z * z) - _VAR_COST
            if statistic > 0.0:
                run += 1.0
            else:
                statistic, run = 0.0, 0.0
            if statistic >= self.threshold:
                age = change_age(self._run(0, int(run)))
        mu = self._mu
        weight = mu * weight + 1.0
        mean_weight = self._mu_mean * mean_weight + 1.0
        mean += x / mean_weight
        r0 = mu * r0 + x * x
        r1 = mu * r1 + x * lag1
        r2 = mu * r2 + x * lag2
        lag2, lag1 = lag1, x
        seen += 1.0
        self._one = [weight, mean, r0, r1, r2, lag1, lag2, f1, f2, inverse_std, statistic,
                     run, seen, armed, mean_weight]
        if seen >= WARMUP and math.fmod(seen, BLOCK) == 0.0:
            self._whiten(np.zeros(1, dtype=np.intp))
        if age:
            self.clear()
        return age

    # ------------------------------------------------------------ the state
    def statistic_of(self, row: int = 0) -> float:
        """Return plant ``row``'s CUSUM S, without writing one plant's numbers back."""
        if self._one is not None and row == 0:
            return self._one[_ROW['statistic']]
        return float(self._values[_ROW['statistic'], row])

    def evidence(self) -> np.ndarray:
        """Return each plant's CUSUM over the threshold, ``(K,)`` (1: a detection)."""
        return self.state.statistic / self.threshold

    def get_state(self, rows: Any = slice(None), prefix: str = 'change_',
                  ) -> dict[str, np.ndarray]:
        """
        Return copies of the state's arrays (of plants ``rows``) under ``<prefix><name>`` keys.

        ``rows`` a list of one index gives one plant's arrays as a one-plant
        detector holds them: what a single-plant estimator's snapshot keeps.
        ``prefix`` starts with ``change_`` (:func:`with_detector_arrays`); an
        estimator with two detectors names them apart.
        """
        return {f'{prefix}{field.name}': getattr(self.state, field.name)[rows].copy()
                for field in dataclasses.fields(DetectorState)}

    def set_state(self, arrays: dict[str, np.ndarray], rows: Any = slice(None),
                  prefix: str = 'change_') -> None:
        """Take over what :meth:`get_state` made (into plants ``rows``; missing keys: afresh)."""
        for field in dataclasses.fields(DetectorState):
            value = arrays.get(f'{prefix}{field.name}')
            target = getattr(self.state, field.name)
            target[rows] = 0.0 if value is None else np.asarray(value, dtype=float)
        if any(f'{prefix}{field.name}' not in arrays
               for field in dataclasses.fields(DetectorState)):
            self.clear(rows)


#: The block test: the errors' means over blocks of this many samples.
BLOCK_LENGTH = 100
#: The block test's variance ratio of the block means it is designed for.
BLOCK_RATIO = 4.0
#: The block test's share of the stated false-alarm rate (the two tests' rates add up).
BLOCK_SHARE = 0.1
#: The blocks the block test's reference needs before any test, and its memory (blocks).
BLOCK_WARMUP = 20
#: See BLOCK_WARMUP.
BLOCK_MEMORY = 40
#: The block test keeps the q of this many blocks of its run, to place the change point.
BLOCK_RING = 64
#: The positions of the block test's numbers in its state array (then its ring of q).
_BLOCK_FIELDS = ('centre', 'sum', 'count', 'last', 'power', 'weight', 'seen', 'statistic',
                 'run')
#: The first of them move with every sample (kept on Python floats between snapshots).
_SAMPLE_FIELDS = 4


class BlockMeanDetector:
    r"""
    A CUSUM of the errors' means over blocks of BLOCK_LENGTH samples: slow changes of the errors.

    :class:`ChangeDetector` centres the errors on their mean over about
    MEAN_MEMORY samples and whitens them by an AR(2) filter learnt on them;
    both are high-pass, and an error that grows at the low frequencies (a
    slow plant whose gain or slow pole moved, seen through a slow input) is
    all but removed: on a tracking plant whose pole moved 0.944 -> 0.963 (13 dB
    coloured noise) rpem's fit's-model errors had 8 times their variance
    after the change, the whitened z^2 1.01-1.06 times theirs
    (docs/tracking_log.md, "Limits", 2026-11-28, session 7). This test takes the
    same errors, less the fit's residual mean (:meth:`prime`), in consecutive
    blocks of B samples; each block mean b is compared with the reference
    variance sigma_b^2 of the block means before it (weights
    mu^k, mu = 1 - 1/BLOCK_MEMORY, over the blocks out of the fits' samples:
    a fit's own residuals understate its errors out of sample at low
    frequencies, 12-19 times on slow plants after fits of about 1000 samples).
    With q = b^2 / sigma_b^2 (clipped at CLIP^2), the CUSUM of the log-likelihood
    ratio of N(0, rho sigma_b^2) against N(0, sigma_b^2), rho = BLOCK_RATIO:

    .. math::

        S \leftarrow \max\big(0,\ S + \tfrac12(1 - 1/\rho)\,q - \tfrac12\ln\rho\big),
        \qquad \text{detection when } S \ge h_b = \ln\frac{1}{\alpha_s B}

    **The false-alarm rate.** Block means of B samples of an error whose
    correlation dies out well within B are close to independent and Gaussian
    (the central limit theorem), and Lorden's bound gives a mean run length of
    at least e^{h_b} blocks: with the block test's share alpha_s = BLOCK_SHARE
    alpha of the stated rate per sample, h_b = 9.21 for alpha = 1e-5; the
    detector beside it takes the rest, (1 - BLOCK_SHARE) alpha, so that the
    two tests together stay within alpha. The reference is learnt on
    BLOCK_WARMUP blocks or more (its own scatter and noise colour slower
    than B samples raise the rate): the measured rates are in
    docs/tracking.md. The reference is kept through the fits (a later fit's
    errors are no larger than an earlier one's under no change: a reference
    that overstates is only slower) and learns on after each test.

    The change point is placed at whole blocks, late rather than early
    (:meth:`_detected`): :meth:`record` returns the samples since then.

    Parameters
    ----------
    false_alarm : float
        The stated false-alarm rate per sample of the detector beside it, in (0, 1):
        this test takes BLOCK_SHARE of it.

    Attributes
    ----------
    threshold : float
        h_b of the CUSUM.
    state : numpy.ndarray
        Its numbers and the ring of its run's q (a snapshot's; all zeros: afresh).

    """

    def __init__(self, false_alarm: float = FALSE_ALARM) -> None:
        self.threshold = threshold(BLOCK_SHARE * false_alarm * BLOCK_LENGTH)
        self._mu = 1.0 - 1.0 / BLOCK_MEMORY
        self._gain = 0.5 * (1.0 - 1.0 / BLOCK_RATIO)
        self._cost = 0.5 * math.log(BLOCK_RATIO)
        self._break_even = self._cost / self._gain
        self._state = np.zeros(len(_BLOCK_FIELDS) + BLOCK_RING)
        self.clear()

    @property
    def state(self) -> np.ndarray:
        """Its numbers and the ring of its run's q (the block's sums written back first)."""
        self._state[:_SAMPLE_FIELDS] = (self._centre, self._total, self._count, self._last)
        return self._state

    def load(self, state: np.ndarray) -> None:
        """Continue from a snapshot's :attr:`state`."""
        self._state[:] = state
        self._centre, self._total, self._count, self._last = (
            self._state[:_SAMPLE_FIELDS].tolist())

    def clear(self) -> None:
        """Start afresh: no reference, no evidence (after a plant change)."""
        self._state[:] = 0.0
        # the block's numbers, which move with every sample, on Python floats
        self._centre, self._total, self._count, self._last = 0.0, 0.0, 0.0, -2.0

    def prime(self, residuals: np.ndarray) -> None:
        """Take a new fit: centre the errors on its residuals' mean; start a new block."""
        self._centre = float(np.mean(residuals)) if len(residuals) else 0.0
        self._total, self._count = 0.0, 0.0

    def record(self, error: float, sample: int) -> int:
        """
        Add the error of sample ``sample`` (an index); return the new regime's age, or 0.

        A sample that does not follow the last one recorded starts a new block
        (a gap: refilled lags, a refused sample).
        """
        if sample != self._last + 1.0:
            total, count = 0.0, 0.0
        else:
            total, count = self._total, self._count
        total += error - self._centre
        count += 1.0
        self._last = float(sample)
        if count < BLOCK_LENGTH:
            self._total, self._count = total, count
            return 0
        self._total, self._count = 0.0, 0.0
        return self._record_block(total / count)

    def _record_block(self, mean: float) -> int:
        """Test a block's mean against the reference, then learn it; the age, or 0."""
        state = self._state
        power, weight, seen, statistic, run = state[_SAMPLE_FIELDS:len(_BLOCK_FIELDS)].tolist()
        if seen >= BLOCK_WARMUP and power > 0.0:
            q = min(mean * mean * weight / power, CLIP * CLIP)
            state[len(_BLOCK_FIELDS) + int(seen) % BLOCK_RING] = q
            statistic += self._gain * q - self._cost
            run = run + 1.0 if statistic > 0.0 else 0.0
            statistic = max(statistic, 0.0)
            if statistic >= self.threshold:
                return self._detected(int(seen), int(run))
        power = self._mu * power + mean * mean
        weight = self._mu * weight + 1.0
        seen += 1.0
        state[_SAMPLE_FIELDS:len(_BLOCK_FIELDS)] = (power, weight, seen, statistic, run)
        return 0

    def _detected(self, seen: int, run: int) -> int:
        """
        Return the new regime's age at a detection by block ``seen``, and start afresh.

        Late rather than early: an old sample in the new plant's fits stays in
        every fit until the next change, where a new sample left out only delays
        the first fit. Every block of a CUSUM's run tends to have q > 1 (a run
        is where the increments were positive), so a GLR over the run takes the
        null blocks before a large change in too. The new regime is the run's
        last blocks whose q all pass the break-even q* = rho ln rho / (rho - 1)
        = 1.85 of the increment (17 % of null blocks do), less the first of
        them, which may hold old samples (a block of 100 samples places the
        change no closer); none left, the detecting sample alone.
        """
        count = min(run, BLOCK_RING)
        q = self._state[len(_BLOCK_FIELDS) + np.arange(seen + 1 - count, seen + 1) % BLOCK_RING]
        below = np.flatnonzero(q < self._break_even)
        first = int(below[-1]) + 1 if below.size else 0
        self.clear()
        return BLOCK_LENGTH * (count - first - 1) if count - first > 1 else 1

    def statistic_of(self) -> float:
        """Return the CUSUM S."""
        return float(self._state[_BLOCK_FIELDS.index('statistic')])


def with_detector_arrays(arrays: dict[str, np.ndarray], own: dict[str, np.ndarray],
                         ) -> dict[str, np.ndarray]:
    """
    Return a snapshot's ``arrays`` with the detector's arrays of ``own`` as zeros if absent.

    A snapshot from before the detector then loads, with the detector started
    afresh (all zeros is its cleared state).
    """
    missing = {key: np.zeros_like(value) for key, value in own.items()
               if key.startswith('change_') and key not in arrays}
    return {**arrays, **missing}


__all__ = ['BLOCK', 'BLOCK_LENGTH', 'BLOCK_MEMORY', 'BLOCK_RATIO', 'BLOCK_RING',
           'BLOCK_SHARE', 'BLOCK_WARMUP', 'BlockMeanDetector', 'CLIP', 'ChangeDetector',
           'DetectorState', 'FALSE_ALARM', 'MEAN_MEMORY', 'MEMORY', 'RING', 'VARIANCE_RATIO',
           'WARMUP', 'change_age', 'threshold', 'with_detector_arrays']
