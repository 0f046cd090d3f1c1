"""
Scenario and sample-stream interfaces shared by the simulator node and the tools.

A :class:`Scenario` describes a plant, its noise and its true parameters. Its
:meth:`Scenario.stream` yields samples in blocks of any size; the samples do
not depend on how they are split into blocks, so the simulator node gives
the same data at every rate and frame size, and equals the offline
:meth:`Scenario.simulate`.
"""

from __future__ import annotations

import abc
import dataclasses
from typing import ClassVar

import numpy as np


@dataclasses.dataclass(frozen=True)
class Truth:
    """True parameters and noise figures of a scenario, in the published naming."""

    parameter_names: tuple[str, ...]
    parameters: np.ndarray
    noise_names: tuple[str, ...]
    noise: np.ndarray


class StreamingFilter:
    """
    A rational filter b(z^-1)/a(z^-1) that keeps its state between blocks.

    Parameters
    ----------
    b, a : array_like
        Numerator and denominator in ascending powers of z^-1 (scipy.signal
        convention), ``a[0] != 0``.

    """

    def __init__(self, b, a) -> None:
        self.b = np.atleast_1d(np.asarray(b, dtype=float))
        self.a = np.atleast_1d(np.asarray(a, dtype=float))
        if self.a.size == 1 and self.b.size > 1:
            # lfilter takes a convolution shortcut for FIR filters, whose rounding
            # depends on the block boundaries; a zero-padded a keeps it recursive.
            self.a = np.concatenate([self.a, np.zeros(self.b.size - 1)])
        self.state = np.zeros(max(len(self.a), len(self.b)) - 1)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Filter the next block ``x`` (shape ``(k,)``) and return the output block."""
        x = np.asarray(x, dtype=float)
        if self.state.size == 0:
            return x * (self.b[0] / self.a[0])
        if x.size == 0:
            # lfilter returns a zero state for an empty block; keep ours
            return x.copy()
        # scipy.signal costs ~1 s to import: load it when a filter first runs, so that
        # `bcid` and the scenario registry start fast.
        from scipy import signal

        out, self.state = signal.lfilter(self.b, self.a, x, zi=self.state)
        return out


class SampleStream(abc.ABC):
    """Yields consecutive samples of one realisation, in blocks of any size."""

    @abc.abstractmethod
    def take(self, count: int) -> tuple[np.ndarray, np.ndarray]:
        """
        Return the next ``count`` samples as ``(y, u)``.

        Returns
        -------
        y : numpy.ndarray, shape ``(count,)``
        u : numpy.ndarray, shape ``(count, r)``

        """


class Scenario(abc.ABC):
    """A plant with its noise model and truth, as in one paper's example."""

    #: Registry name, as in the simulator's ``scenario`` parameter.
    name: ClassVar[str] = ''
    order: int = 1
    num_inputs: int = 1
    feedthrough: bool = False

    @abc.abstractmethod
    def truth(self) -> Truth:
        """Return the true parameters and noise figures."""

    @abc.abstractmethod
    def stream(self, rng: np.random.Generator) -> SampleStream:
        """Return a fresh sample stream drawing from ``rng``."""

    def simulate(self, count: int,
                 seed: int | np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Return ``count`` samples ``(y, u)`` of the realisation with ``seed``."""
        return self.stream(np.random.default_rng(seed)).take(count)
