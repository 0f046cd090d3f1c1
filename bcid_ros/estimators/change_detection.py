r"""
The sequential test for a plant change: CUSUMs on the whitened one-step errors.

An estimator of a plant that has changed predicts with the old model, so its
one-step errors grow: e(t) = v(t) + (G_new - G_old) u(t) has a larger variance
and, with an input or a load off zero, a shifted mean. :class:`ChangeDetector`
accumulates that evidence sample by sample with Page's CUSUM (Page 1954;
Basseville and Nikiforov, *Detection of Abrupt Changes*, 1993, sec. 2.2),
so that a large change is seen within a few samples and a small persistent
one once its evidence has added up.

**The errors.** Each plant gives its normalised one-step error (the
estimator's a-priori error over the square root of its gain term, e/sqrt(s)).
The detector keeps a reference of them with memory ``memory`` (weights
mu^(T-t), mu = 1 - 1/memory): the mean m and the autocovariances R_0, R_1,
R_2 of e - m. From these, Levinson-Durbin gives the AR(2) predictor of the
error's own colour, x(t) = (e(t) - m) - f_1 (e(t-1) - m) - f_2 (e(t-2) - m),
with variance v_2, and the test statistic is z(t) = x(t)/sqrt(v_2): N(0, 1)
and white as long as the reference describes the errors (coloured errors,
as an output-error model's under coloured noise, would otherwise make the
sums of the CUSUMs far more variable than their design). The filter is
recomputed every ``BLOCK`` samples; each sample is tested before it joins
the reference.

**Three CUSUMs**, each the log-likelihood ratio of a Gaussian alternative
against N(0, 1), clipped at ``CLIP`` standard deviations so that one spike
adds at most a third of the threshold (a clipped increment only lowers the
statistic, so the bound below still holds):

.. math::

    S_v &\leftarrow \max\big(0,\ S_v + \tfrac12(1 - 1/\rho) z^2 - \tfrac12\ln\rho\big)
        && \text{variance} \times\rho,\ \rho = \text{VARIANCE\_RATIO} \\
    S_\pm &\leftarrow \max\big(0,\ S_\pm \pm \delta z - \tfrac12\delta^2\big)
        && \text{mean} \pm\delta,\ \delta = \text{MEAN\_SHIFT}

A change is detected when one of them reaches h. The estimated change point
is the sample after that CUSUM's last zero (the maximum-likelihood change
time of the CUSUM; Basseville and Nikiforov, sec. 2.2.2).

**The threshold from the false-alarm rate.** For a CUSUM of log-likelihood
ratios, exp(S) restarted at every zero is a non-negative supermartingale
under the null, so the mean run length to a false alarm is at least e^h
(Lorden 1971; Basseville and Nikiforov, eq. 5.2.49). Three CUSUMs give
at most 3 e^(-h) false alarms per sample, so
h = ln(3 / ``false_alarm``) = 12.61 for the stated rate of 1 per 100,000
samples. The bound is conservative: Siegmund's approximation for the
mean CUSUMs (reference k = delta/2, threshold h/delta in sigma units,
b = h/delta + 1.166) gives an ARL of about (e^(2kb) - 2kb - 1)/(2k^2) = 4.3e6
each; the measured rates are in docs/tracking.md. It assumes what the
reference estimates (Gaussian, AR(2)-coloured errors); heavier tails raise it.

**Detection delay** is about h over the mean increment under the change:
(z^2/6 - 0.203) for the variance, so 4 samples for an error variance 25
times the reference, 42 for 3 times, 270 for 1.5 times; 100 samples for a
mean shift of 0.5 sigma, 34 for 1 sigma.

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
VARIANCE_RATIO = 1.5
#: The mean shift (in standard deviations) the two mean CUSUMs are designed for.
MEAN_SHIFT = 0.5
#: A sample's z is clipped at this many standard deviations (a spike adds at most 4.0).
CLIP = 5.0
#: The number of CUSUMs (variance, mean up, mean down), for the threshold.
CUSUMS = 3
#: The reference's memory (samples), and the effective samples it needs before any test.
MEMORY = 2000
#: See MEMORY.
WARMUP = 250
#: The whitening filter is recomputed every this many samples.
BLOCK = 64
#: Largest reflection coefficient of the whitening filter.
MAX_REFLECTION = 0.995

#: The increments' constants.
_VAR_GAIN = 0.5 * (1.0 - 1.0 / VARIANCE_RATIO)
_VAR_COST = 0.5 * math.log(VARIANCE_RATIO)
_MEAN_COST = 0.5 * MEAN_SHIFT * MEAN_SHIFT
_CLIP2 = CLIP * CLIP


def threshold(false_alarm: float = FALSE_ALARM) -> float:
    """Return h = ln(CUSUMS / false_alarm), from Lorden's bound ARL >= e^h per CUSUM."""
    if not 0.0 < false_alarm < 1.0:
        raise ValueError(f'false_alarm must be in (0, 1), got {false_alarm!r}')
    return math.log(CUSUMS / false_alarm)


def siegmund_arl(shift: float, h: float) -> float:
    r"""
    Return Siegmund's approximation of a Gaussian mean CUSUM's ARL under no change.

    For the LLR CUSUM of a mean shift ``shift`` (sigma units) with threshold
    ``h``: reference k = shift/2, threshold b = h/shift + 1.166 in sigma units,
    :math:`ARL \approx (e^{2kb} - 2kb - 1)/(2k^2)` (Siegmund 1985; Basseville
    and Nikiforov, eq. 5.2.44 with drift -k).
    """
    k = 0.5 * shift
    b = h / shift + 1.166
    return (math.exp(2.0 * k * b) - 2.0 * k * b - 1.0) / (2.0 * k * k)


@dataclasses.dataclass
class DetectorState:
    """The arrays of a :class:`ChangeDetector`, each ``(K,)`` (see its docstring)."""

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
    s_var: np.ndarray
    s_up: np.ndarray
    s_down: np.ndarray
    run_var: np.ndarray
    run_up: np.ndarray
    run_down: np.ndarray
    seen: np.ndarray
    armed: np.ndarray


class ChangeDetector:
    """
    CUSUMs of the whitened normalised errors of K plants (see the module docstring).

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
        h of the CUSUMs.
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
        count = 1 if plants is None else int(plants)
        self.state = DetectorState(*[np.zeros(count) for _ in
                                     range(len(dataclasses.fields(DetectorState)))])
        self.clear()

    # ------------------------------------------------------------- the API
    def clear(self, rows: Any = slice(None)) -> None:
        """Start plants ``rows`` afresh: no reference, no evidence (after a restart)."""
        for field in dataclasses.fields(DetectorState):
            getattr(self.state, field.name)[rows] = 0.0

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
        st = self.state
        rows = np.asarray(rows, dtype=np.intp)
        error = np.asarray(error, dtype=float)
        age = np.zeros(rows.shape[0], dtype=np.int64)
        x = error - st.mean[rows]
        armed = st.armed[rows] > 0.0
        if armed.any():
            at = rows[armed]
            z = (x[armed] - st.f1[at] * st.lag1[at] - st.f2[at] * st.lag2[at]) \
                * st.inverse_std[at]
            z = np.minimum(np.maximum(z, -CLIP), CLIP)
            age[armed] = self._cusums(at, z)
        self._learn(rows, x, error)
        changed = rows[age > 0]
        if changed.size:
            self.clear(changed)
        return age

    # ------------------------------------------------------- the statistics
    def _cusums(self, rows: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Step the three CUSUMs of ``rows``; return the ages of the detections (0: none)."""
        st = self.state
        h = self.threshold
        ages = np.zeros(rows.shape[0], dtype=np.int64)
        for statistic, run, increment in (
                (st.s_var, st.run_var, _VAR_GAIN * (z * z) - _VAR_COST),
                (st.s_up, st.run_up, MEAN_SHIFT * z - _MEAN_COST),
                (st.s_down, st.run_down, -MEAN_SHIFT * z - _MEAN_COST)):
            value = statistic[rows] + increment
            positive = value > 0.0
            value = np.where(positive, value, 0.0)
            length = np.where(positive, run[rows] + 1.0, 0.0)
            statistic[rows], run[rows] = value, length
            fired = (value >= h) & (ages == 0)
            ages[fired] = length[fired].astype(np.int64)
        return ages

    def _learn(self, rows: np.ndarray, x: np.ndarray, error: np.ndarray) -> None:
        """Add the samples to the reference of ``rows``; refit the whitening when due."""
        st = self.state
        mu = self._mu
        weight = mu * st.weight[rows] + 1.0
        st.weight[rows] = weight
        st.mean[rows] += x / weight
        lag1, lag2 = st.lag1[rows], st.lag2[rows]
        st.r0[rows] = mu * st.r0[rows] + x * x
        st.r1[rows] = mu * st.r1[rows] + x * lag1
        st.r2[rows] = mu * st.r2[rows] + x * lag2
        st.lag2[rows], st.lag1[rows] = lag1, x
        seen = st.seen[rows] + 1.0
        st.seen[rows] = seen
        due = (seen >= WARMUP) & (np.fmod(seen, BLOCK) == 0.0)
        if due.any():
            self._whiten(rows[due])

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
        """:meth:`record_rows` of one plant on Python floats (the same operations, same bits)."""
        st = self.state
        x = error - float(st.mean[0])
        age = 0
        if st.armed[0]:
            z = (x - float(st.f1[0]) * float(st.lag1[0])
                 - float(st.f2[0]) * float(st.lag2[0])) * float(st.inverse_std[0])
            z = -CLIP if z < -CLIP else (CLIP if z > CLIP else z)
            age = self._cusums_one(z)
        mu = self._mu
        weight = mu * float(st.weight[0]) + 1.0
        st.weight[0] = weight
        st.mean[0] += x / weight
        lag1, lag2 = float(st.lag1[0]), float(st.lag2[0])
        st.r0[0] = mu * float(st.r0[0]) + x * x
        st.r1[0] = mu * float(st.r1[0]) + x * lag1
        st.r2[0] = mu * float(st.r2[0]) + x * lag2
        st.lag2[0], st.lag1[0] = lag1, x
        seen = float(st.seen[0]) + 1.0
        st.seen[0] = seen
        if seen >= WARMUP and math.fmod(seen, BLOCK) == 0.0:
            self._whiten(np.zeros(1, dtype=np.intp))
        if age:
            self.clear()
        return age

    def _cusums_one(self, z: float) -> int:
        st = self.state
        h = self.threshold
        age = 0
        for statistic, run, increment in (
                (st.s_var, st.run_var, _VAR_GAIN * (z * z) - _VAR_COST),
                (st.s_up, st.run_up, MEAN_SHIFT * z - _MEAN_COST),
                (st.s_down, st.run_down, -MEAN_SHIFT * z - _MEAN_COST)):
            value = float(statistic[0]) + increment
            if value > 0.0:
                length = float(run[0]) + 1.0
            else:
                value, length = 0.0, 0.0
            statistic[0], run[0] = value, length
            if value >= h and not age:
                age = int(length)
        return age

    # ------------------------------------------------------------ the state
    def evidence(self) -> np.ndarray:
        """Return each plant's largest CUSUM over the threshold, ``(K,)`` (1: a detection)."""
        st = self.state
        return np.maximum(np.maximum(st.s_var, st.s_up), st.s_down) / self.threshold

    def get_state(self) -> dict[str, np.ndarray]:
        """Return copies of the state's arrays under ``change_<name>`` keys."""
        return {f'change_{field.name}': getattr(self.state, field.name).copy()
                for field in dataclasses.fields(DetectorState)}

    def set_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Take over what :meth:`get_state` made (missing keys: start afresh)."""
        for field in dataclasses.fields(DetectorState):
            value = arrays.get(f'change_{field.name}')
            target = getattr(self.state, field.name)
            target[:] = 0.0 if value is None else np.asarray(value, dtype=float)
        if any(f'change_{field.name}' not in arrays
               for field in dataclasses.fields(DetectorState)):
            self.clear()


__all__ = ['BLOCK', 'CLIP', 'CUSUMS', 'ChangeDetector', 'DetectorState', 'FALSE_ALARM',
           'MEAN_SHIFT', 'MEMORY', 'VARIANCE_RATIO', 'WARMUP', 'siegmund_arl', 'threshold']
