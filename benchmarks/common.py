"""Shared pieces of the benchmarks: result rows and per-call timing."""

from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import numpy as np


@dataclasses.dataclass
class Result:
    """One measured figure, with the target it is held against (if any)."""

    section: str
    metric: str
    value: float
    unit: str
    target: str = ''
    met: bool | None = None
    note: str = ''

    def cells(self) -> list[str]:
        """Return the Markdown table cells of this row."""
        verdict = {True: 'met', False: '**missed**', None: ''}[self.met]
        return [self.metric, f'{self.value:.4g} {self.unit}', self.target, verdict, self.note]


def time_each(calls: Sequence[Callable[[], object]]) -> np.ndarray:
    """Call each callable once and return the wall time of each call in microseconds."""
    clock = time.perf_counter_ns
    times = np.empty(len(calls))
    for k, call in enumerate(calls):
        start = clock()
        call()
        times[k] = clock() - start
    return times / 1000.0


def per_sample_us(update: Callable[[float, np.ndarray], object], y: np.ndarray,
                  u: np.ndarray) -> np.ndarray:
    """Return the time of ``update(y[t], u[t])`` for every t, in microseconds."""
    clock = time.perf_counter_ns
    y_list = y.tolist()
    times = np.empty(len(y_list))
    for t, value in enumerate(y_list):
        row = u[t]
        start = clock()
        update(value, row)
        times[t] = clock() - start
    return times / 1000.0


def best_of(measure: Callable[[], np.ndarray], repeats: int = 3) -> np.ndarray:
    """
    Return the per-call times of the repeat with the lowest median.

    A repeat disturbed by another process on this shared 2-core machine only
    ever makes calls slower, so the fastest repeat is the best estimate of the
    cost (the same reasoning as timeit's minimum).
    """
    runs = [measure() for _ in range(repeats)]
    return min(runs, key=np.median)


def summary(times_us: np.ndarray) -> tuple[float, float]:
    """Return (median, 99th percentile) of per-call times."""
    return float(np.median(times_us)), float(np.percentile(times_us, 99))
