"""Shared helpers of the reproductions: progress, Markdown tables, figures."""

from __future__ import annotations

import sys
import time
from typing import Iterable

import numpy as np


class Progress:
    """
    Print ``label: k/N (eta ...)`` to stderr at most twice a second.

    Parameters
    ----------
    label : str
        What is running, printed in front of the counter.
    stream : file-like, optional
        Where to print; stderr by default.

    """

    def __init__(self, label: str, stream=None) -> None:
        self.label = label
        self.stream = stream if stream is not None else sys.stderr

    def __call__(self, iterable: Iterable, total: int, what: str = '') -> Iterable:
        """Yield from ``iterable`` while reporting progress over ``total`` items."""
        start = last = time.monotonic()
        tag = f'{self.label} {what}'.strip()
        interactive = getattr(self.stream, 'isatty', lambda: False)()
        done = 0
        for done, item in enumerate(iterable, 1):
            yield item
            now = time.monotonic()
            if now - last >= (0.5 if interactive else 10.0) or done == total:
                last = now
                eta = (now - start) / done * (total - done)
                end = '\r' if interactive and done < total else '\n'
                self.stream.write(f'{tag}: {done}/{total} ({now - start:.1f} s, '
                                  f'eta {eta:.0f} s){end}')
                self.stream.flush()
        if done == 0:
            self.stream.write(f'{tag}: nothing to do\n')


def mean_and_stderr(values: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return the mean over ``axis`` and its Monte Carlo standard error."""
    values = np.asarray(values, dtype=float)
    count = values.shape[axis]
    stderr = values.std(axis=axis, ddof=1) / np.sqrt(count) if count > 1 else np.zeros_like(
        values.mean(axis=axis))
    return values.mean(axis=axis), stderr


def relative_error(theta: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Return delta = ||theta - truth|| / ||truth|| over the last axis (Ding et al., sec. III)."""
    return np.linalg.norm(np.asarray(theta) - truth, axis=-1) / np.linalg.norm(truth)


def pyplot():
    """Return matplotlib.pyplot on the non-interactive Agg backend."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt
