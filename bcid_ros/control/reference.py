"""
Built-in reference signals for excitation: square wave, PRBS from a seed, none.

The signals count samples (one per measured output), not seconds, so the
excitation is the same at any rate and in replays.
"""

from __future__ import annotations

import numpy as np

#: The allowed values of ``reference_signal``.
REFERENCE_SIGNALS = ('none', 'square', 'prbs')


class ReferenceGenerator:
    """
    Produce the excitation added to the setpoint, one value per sample.

    Parameters
    ----------
    signal : str
        ``square``: +amplitude for the first half of each period, -amplitude
        for the second; ``prbs``: a pseudo-random binary sequence, +-amplitude
        with equal probability, each level held ``period`` samples, drawn
        from ``numpy.random.default_rng(seed)``; ``none``: 0.
    amplitude : float
        Level of the signal, >= 0.
    period : int
        Square: samples per period (>= 2); PRBS: samples each level is held
        (>= 1).
    seed : int
        Seed of the PRBS.

    Raises
    ------
    ValueError
        For an unknown signal, a negative or non-finite amplitude or a period
        out of range.

    """

    def __init__(self, signal: str = 'none', *, amplitude: float = 1.0, period: int = 100,
                 seed: int = 0) -> None:
        if signal not in REFERENCE_SIGNALS:
            raise ValueError(f'parameter \'reference_signal\' must be one of '
                             f'{", ".join(REFERENCE_SIGNALS)}, got {signal!r}')
        if not (np.isfinite(amplitude) and amplitude >= 0.0):
            raise ValueError(f'parameter \'reference_amplitude\' must be a number in '
                             f'[0, inf), got {amplitude!r}')
        smallest = 2 if signal == 'square' else 1
        if int(period) != period or period < smallest:
            raise ValueError(f'parameter \'reference_period\' must be an integer >= '
                             f'{smallest} for {signal!r}, got {period!r}')
        self.signal = signal
        self.amplitude = float(amplitude)
        self.period = int(period)
        self._rng = np.random.default_rng(seed)
        self._sample = 0
        self._level = 0.0

    def next(self) -> float:
        """Return the value of the current sample and advance by one."""
        k = self._sample
        self._sample += 1
        if self.signal == 'square':
            return self.amplitude if (k % self.period) < self.period / 2 else -self.amplitude
        if self.signal == 'prbs':
            if k % self.period == 0:
                self._level = self.amplitude if self._rng.integers(2) else -self.amplitude
            return self._level
        return 0.0


__all__ = ['REFERENCE_SIGNALS', 'ReferenceGenerator']
