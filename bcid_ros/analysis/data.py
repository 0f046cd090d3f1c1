"""Read a bag's ``/samples`` into arrays for the offline analysis."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from bcid_ros.bag.reader import BagReader, FLOAT64_MULTI_ARRAY
from bcid_ros.errors import BcidError
from bcid_ros.identifier.layouts import decode_samples

SAMPLES_TOPIC = '/samples'

#: Report reading progress every this many messages.
PROGRESS_EVERY = 50000


def read_samples(path: str | Path, progress: Callable[[str], None] | None = None
                 ) -> tuple[np.ndarray, np.ndarray, int]:
    """
    Return ``(y, u, dropped)`` from the ``/samples`` topic of a bag.

    Frames are unpacked into their samples. Malformed messages and samples
    with NaN/Inf are dropped and counted, as the identifier node does.

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
        or the row width changes.

    """
    reader = BagReader(path)
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
        finite = np.isfinite(block).all(axis=1)
        dropped += int(np.count_nonzero(~finite))
        rows.append(block[finite])
        if progress is not None and count % PROGRESS_EVERY == 0:
            progress(f'read {count} of {info.count} messages')
    if not rows or sum(block.shape[0] for block in rows) == 0:
        raise BcidError(f'{path}: topic {SAMPLES_TOPIC} holds no usable sample')
    data = np.concatenate(rows)
    return np.ascontiguousarray(data[:, 0]), np.ascontiguousarray(data[:, 1:]), dropped


__all__ = ['SAMPLES_TOPIC', 'read_samples']
