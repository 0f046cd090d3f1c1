"""
The samples of the recursive BCIV estimator: the window that holds eta and p (eqs. 54, 68-70).

Ikenoue et al. (2008), eq. (54): the IV-type vector eta holds the last
m = n + 2l inputs, and with the causal delay of eqs. (68)-(70) the regressor
p and z of the same update lie l - 1 samples back in the same window. The
window is a ring of [-z, w] pairs written backwards, so that the newest m
samples are contiguous; a dead time d pairs z(t) with w(t - d) from a delay
line of the last d inputs ("Dead time" in docs/bciv.md).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

#: Samples the ring takes before it moves its window back.
RING_SAMPLES = 512


class SampleHistory:
    """
    The ring of [-z, w] pairs and the delay line of the inputs.

    Row k of :attr:`window` (shape ``(m, 2)``) is ``[-z(t - k), w(t - k - d)]``.
    :meth:`restart` empties the window (after a gap, or an undone step) and
    the delay line's count, not its position: a step transaction that may
    change the delay line saves :attr:`line` and :attr:`line_position`.

    Parameters
    ----------
    m : int
        The length of the IV-type vector (54).
    gathers : tuple of numpy.ndarray
        The gathers of eta and [p; -z] from the flattened window
        (:meth:`~bcid_ros.estimators.bciv.solver.BcivSolver.window_indices`).
    order : int
        n.
    lags : sequence of int
        The lags k of b_k: 1..n, or 0..n with feedthrough.
    delay : int
        The dead time d of the input.

    """

    def __init__(self, m: int, gathers: tuple[np.ndarray, np.ndarray], order: int,
                 lags: Sequence[int], delay: int) -> None:
        self.m, self.order, self.delay = m, order, delay
        self.feedthrough = 0 in lags
        self.ring = np.zeros(2 * (RING_SAMPLES + m))
        self.line = np.zeros(delay)
        self._gather = np.concatenate(gathers)
        # p(t) of the undelayed ARX equation from the newest n rows of the window
        # (before the push): -z(t-j) at 2(j-1), w(t-j) at 2(j-1) + 1
        self._error_gather = np.array([2 * (j - 1) for j in range(1, order + 1)]
                                      + [2 * (k - 1) + 1 for k in lags if k > 0], dtype=np.intp)
        self._error_theta = np.array(list(range(order)) + [
            order + i for i, k in enumerate(lags) if k > 0], dtype=np.intp)
        self.clear()

    def clear(self) -> None:
        """Empty the ring and the delay line (the state after construction)."""
        self.ring[:] = 0.0
        self.start = 2 * RING_SAMPLES
        self.filled = 0
        self.line[:] = 0.0
        self.line_position = 0
        self.line_filled = 0

    def restart(self) -> None:
        """Empty the window and let the delay line refill (after a gap)."""
        self.window[:] = 0.0
        self.filled = 0
        self.line_filled = 0

    @property
    def window(self) -> np.ndarray:
        """Return the (m, 2) window of [-z, w] (row k: sample t - k), a view into the ring."""
        return self.ring[self.start:self.start + 2 * self.m].reshape(-1, 2)

    def delayed_input(self, w: float) -> float | None:
        """Return the input w(t - d) that the next push adds, or None while the line fills."""
        delay = self.delay
        if not delay:
            return w
        if self.line_filled < delay:
            return None
        return float(self.line[self.line_position])

    def push(self, z: float, w: float) -> bool:
        """
        Add sample (z(t), w(t - d)) to the history; return whether the window is full.

        With a dead time d the history pairs z(t) with w(t - d), read from a
        delay line of the last d inputs: the IV-type vector and p_t then
        shift together by d, so that eqs. (54)-(75) hold unchanged for the
        shifted input (docs/bciv.md, "Dead time"). The first d samples only
        fill the delay line.
        """
        delay = self.delay
        if delay:
            position = self.line_position
            delayed = self.line[position]
            self.line[position] = w
            self.line_position = position + 1 if position + 1 < delay else 0
            if self.line_filled < delay:
                self.line_filled += 1
                return False
            w = delayed
        m = self.m
        ring = self.ring
        start = self.start - 2
        if start < 0:
            # move the newest m - 1 samples to the end of the ring
            start = 2 * RING_SAMPLES
            ring[start + 2:] = ring[:2 * m - 2]
        ring[start] = -z
        ring[start + 1] = w
        self.start = start
        if self.filled < m:
            self.filled += 1
            return self.filled == m
        return True

    def sample(self) -> np.ndarray:
        """Return [eta; p; -z] of eqs. (54), (68)-(70) from the newest window."""
        start = self.start
        return self.ring[start:start + 2 * self.m][self._gather]

    def equation_error(self, y: float, w: float, theta: np.ndarray) -> float:
        """Return the equation error z(t) - p(t)' theta of a new sample, before its push."""
        window = self.ring[self.start:self.start + 2 * self.order]
        error = y - float(window[self._error_gather].dot(theta[self._error_theta]))
        if self.feedthrough:
            error -= float(theta[self.order]) * w
        return error
