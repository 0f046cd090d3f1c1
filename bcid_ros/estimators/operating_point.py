"""
The operating point of a plant: recursive means for ``detrend: mean`` and a centring check.

A real plant runs around an operating point (y0, u0) and the ARX model of
the estimators describes the deviations from it. :class:`RunningMean`
estimates the point recursively (with the estimator's forgetting factor) so
that the deviations can be regressed; :class:`CentringMonitor` tells, with
``detrend: none``, when the data are far from centred (docs/estimators.md,
"Operating point").
"""

from __future__ import annotations

import math

import numpy as np

#: Larger samples (their squares overflow) do not enter the means or the centring check.
HUGE = 1e150
#: Not centred: |mean| above this many standard deviations of the signal. At one,
#: the offset carries more of the mean square than the variation does, and an
#: ARX model without the operating point is visibly biased (docs/estimators.md).
CENTRING_SIGMAS = 1.0
#: The check looks at about this many recent samples (exponential memory).
CENTRING_MEMORY = 1000
#: It takes one sample in this many (the statistic needs no more, and costs less).
CENTRING_STRIDE = 16


def operating_point_names(num_inputs: int) -> tuple[str, ...]:
    """Return the names of the operating point, ``('y', 'u1', ..., 'ur')``."""
    return ('y',) + tuple(f'u{i}' for i in range(1, num_inputs + 1))


class RunningMean:
    r"""
    Recursive weighted means of y and u_1 ... u_r.

    .. math::

        \tau_m(t) = \lambda\tau_m(t-1) + 1, \qquad
        m(t) = m(t-1) + [x(t) - m(t-1)] / \tau_m(t)

    so that :math:`m(t) = \sum_i \lambda^{t-i} x(i) / \sum_i \lambda^{t-i}`,
    the weighted sample mean (the plain mean with :math:`\lambda = 1`).

    Parameters
    ----------
    num_inputs : int
        r.

    """

    def __init__(self, num_inputs: int) -> None:
        self.mean = np.zeros(1 + num_inputs)
        self.weight = 0.0
        # the means and weight before the last centre(), for undo()
        self._previous = np.zeros(1 + num_inputs)
        self._previous_weight = 0.0

    def centre(self, y: float, u: np.ndarray, lam: float) -> tuple[float, np.ndarray]:
        """Update the means with sample (y, u) and return the sample minus them."""
        if not (abs(y) < HUGE and (np.abs(u) < HUGE).all()):
            # a sample whose square overflows is refused by the estimator's gate anyway:
            # it must not move the means for thousands of samples to come
            return self.apply(y, u)
        mean = self.mean
        self._previous[:] = mean
        self._previous_weight = self.weight
        self.weight = lam * self.weight + 1.0
        gain = 1.0 / self.weight
        mean[0] += (y - mean[0]) * gain
        mean[1:] += (u - mean[1:]) * gain
        return y - mean[0], u - mean[1:]

    def undo(self) -> None:
        """Take the last sample given to :meth:`centre` back out of the means."""
        self.mean[:] = self._previous
        self.weight = self._previous_weight

    def apply(self, y: float, u: np.ndarray) -> tuple[float, np.ndarray]:
        """Return the sample minus the means, without updating them (adaptation held)."""
        return y - self.mean[0], u - self.mean[1:]

    def clear(self) -> None:
        """Forget the means."""
        self.mean[:] = 0.0
        self.weight = 0.0


class CentringMonitor:
    """
    Warn when the data are not centred: |mean| > CENTRING_SIGMAS std over the recent samples.

    One sample in ``CENTRING_STRIDE`` updates exponentially weighted means
    and mean squares with a memory of about ``CENTRING_MEMORY`` samples. A
    channel is not centred when its mean exceeds ``CENTRING_SIGMAS`` times
    its standard deviation: the offset then dominates the signal, and a
    model without an operating point regresses it (use ``detrend: mean``).

    Parameters
    ----------
    num_inputs : int
        r.

    """

    def __init__(self, num_inputs: int) -> None:
        self.names = operating_point_names(num_inputs)
        self.mean = np.zeros(1 + num_inputs)
        self.square = np.zeros(1 + num_inputs)
        self.weight = 0.0
        self._skip = 0

    def take(self, y: float, u: np.ndarray) -> None:
        """Account for one sample (one in CENTRING_STRIDE is used)."""
        if self._skip:
            self._skip -= 1
            return
        self._skip = CENTRING_STRIDE - 1
        self._take_row(np.concatenate(([y], u)))

    def take_rows(self, rows: np.ndarray) -> None:
        """Account for consecutive samples ``[y, u1, ..., ur]``: :meth:`take` on each, at once."""
        count, first = rows.shape[0], self._skip
        if first >= count:
            self._skip -= count
            return
        for row in rows[first::CENTRING_STRIDE]:
            self._take_row(row)
        last = first + (count - 1 - first) // CENTRING_STRIDE * CENTRING_STRIDE
        self._skip = CENTRING_STRIDE - 1 - (count - 1 - last)

    def _take_row(self, row: np.ndarray) -> None:
        if not (np.abs(row) < HUGE).all():
            return  # its square would overflow; the gate refuses such a sample anyway
        self.weight = min(self.weight + 1.0, CENTRING_MEMORY / CENTRING_STRIDE)
        gain = 1.0 / self.weight
        self.mean += (row - self.mean) * gain
        self.square += (row * row - self.square) * gain

    def problem(self) -> str:
        """Return a warning naming the channels that are not centred, or ''."""
        if self.weight < 2.0:
            return ''
        variance = np.maximum(self.square - self.mean * self.mean, 0.0)
        far = np.abs(self.mean) > CENTRING_SIGMAS * np.sqrt(variance)
        far &= self.mean != 0.0
        if not far.any():
            return ''
        worst = ', '.join(f'{name} mean {mean:.4g} std {math.sqrt(var):.3g}'
                          for name, mean, var, bad in zip(self.names, self.mean, variance, far)
                          if bad)
        return f'data not centred ({worst}): set detrend: mean'


__all__ = ['CENTRING_MEMORY', 'CENTRING_SIGMAS', 'CENTRING_STRIDE', 'CentringMonitor',
           'RunningMean', 'operating_point_names']
