"""Read a bag's ``/samples``, or a CSV log, into arrays for the offline analysis."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from bcid_ros.bag.csv_samples import CsvSamples, samples_source
from bcid_ros.bag.reader import BagReader, FLOAT64_MULTI_ARRAY
from bcid_ros.errors import BcidError
from bcid_ros.identifier.layouts import decode_samples

SAMPLES_TOPIC = '/samples'

#: Report reading progress every this many messages.
PROGRESS_EVERY = 50000


def read_samples(path: str | Path, progress: Callable[[str], None] | None = None,
                 columns: str | None = None, time_column: str | None = None
                 ) -> tuple[np.ndarray, np.ndarray, int]:
    """
    Return ``(y, u, dropped)`` from the ``/samples`` topic of a bag, or from a CSV log.

    Frames are unpacked into their samples. Malformed messages and samples
    with NaN/Inf (in a CSV log also empty cells) are dropped and counted, as
    the identifier node does.

    Parameters
    ----------
    path : str or pathlib.Path
        A bag, or a CSV log (suffix ``.csv``, :mod:`bcid_ros.bag.csv_samples`).
    progress : callable, optional
        Called with a line of progress now and then.
    columns, time_column : str, optional
        For a CSV log: the columns (``--columns``) and the time column.

    Returns
    -------
    y : numpy.ndarray, shape ``(N,)``
    u : numpy.ndarray, shape ``(N, r)``
    dropped : int
        Samples (or malformed messages) left out.

    Raises
    ------
    BcidError
        If the bag cannot be read, has no ``/samples`` topic or no sample in it,
        or the row width changes; if the CSV log cannot be read.

    """
    source = samples_source(Path(path), columns, time_column)
    if isinstance(source, CsvSamples):
        return _usable([source.rows], 0, f'{path}: the CSV log')
    reader = BagReader(source)
    info = reader.require(SAMPLES_TOPIC, FLOAT64_MULTI_ARRAY)
    rows: list[np.ndarray] = []
    dropped = 0
    width = None
    for count, (_, message) in enumerate(reader.float64_multi_arrays(SAMPLES_TOPIC), 1):
        try:
            block = decode_samples(message, None if width is None else width - 1)
        except ValueError:
            dropped += 1
            continue
        width = block.shape[1]
        rows.append(block)
        if progress is not None and count % PROGRESS_EVERY == 0:
            progress(f'read {count} of {info.count} messages')
    return _usable(rows, dropped, f'{path}: topic {SAMPLES_TOPIC}')


def _usable(rows: list[np.ndarray], dropped: int, where: str
            ) -> tuple[np.ndarray, np.ndarray, int]:
    """Return ``(y, u, dropped)`` of the rows without the samples with NaN/Inf (counted)."""
    data = np.concatenate(rows) if rows else np.zeros((0, 2))
    finite = np.isfinite(data).all(axis=1)
    data = data[finite]
    if data.shape[0] == 0:
        raise BcidError(f'{where} holds no usable sample (none, or all malformed or with '
                        'NaN/Inf)')
    dropped += int(np.count_nonzero(~finite))
    return np.ascontiguousarray(data[:, 0]), np.ascontiguousarray(data[:, 1:]), dropped


__all__ = ['SAMPLES_TOPIC', 'read_samples']
