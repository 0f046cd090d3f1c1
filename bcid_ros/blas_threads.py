"""
One BLAS thread for the batch fits and the nodes, without threadpoolctl.

The batch fits of ``bcid analyze`` factor tall, narrow matrices (thousands of
rows, a few tens of columns) hundreds of times; the estimators' checks in a
node factor a few such every few hundred samples. OpenBLAS splits each such
call over its threads, and on a machine whose cores are busy the threads wait
for each other: one SVD of 7000 x 25 took 3.3 ms of CPU with one thread and
284 ms with the default threads on this project's loaded 2-core machine
(docs/analyze.md, *Speed*). :func:`single_threaded_blas` sets every OpenBLAS
library loaded in the process (numpy's and scipy's wheels each bring one) to
one thread for the duration of a ``with`` block and restores the previous
counts after it; :func:`set_one_blas_thread` sets them for good (a node).
Both go through the libraries' own ``*openblas_set_num_threads`` functions,
which is what threadpoolctl does. Where no OpenBLAS is found (another BLAS,
another operating system), they do nothing: the environment variable
``OPENBLAS_NUM_THREADS=1`` (or ``OMP_NUM_THREADS``, ``MKL_NUM_THREADS``) set
before Python starts does the same for every library.
"""
from __future__ import annotations

import contextlib
import ctypes
from pathlib import Path
from typing import Callable, Iterator

#: Symbol prefixes and suffixes of ``openblas_set_num_threads`` in the wheels'
#: builds (plain OpenBLAS; scipy-openblas with 32- and 64-bit integers).
_SYMBOLS = (('', ''), ('scipy_', ''), ('scipy_', '64_'), ('', '64_'))
#: Where the shared libraries mapped into this process are listed (Linux).
_MAPS = Path('/proc/self/maps')


def openblas_libraries() -> list[str]:
    """Return the paths of the OpenBLAS shared libraries loaded in this process (Linux)."""
    try:
        lines = _MAPS.read_text().splitlines()
    except OSError:
        return []
    paths = []
    for line in lines:
        path = line.split()[-1] if len(line.split()) >= 6 else ''
        if 'openblas' in Path(path).name.lower() and path not in paths:
            paths.append(path)
    return paths


def _controls(path: str) -> tuple[Callable[[int], None], Callable[[], int]] | None:
    """Return (set, get) of one library's thread count, or None when it has neither."""
    try:
        library = ctypes.CDLL(path)
    except OSError:
        return None
    for prefix, suffix in _SYMBOLS:
        setter = getattr(library, f'{prefix}openblas_set_num_threads{suffix}', None)
        getter = getattr(library, f'{prefix}openblas_get_num_threads{suffix}', None)
        if setter is not None and getter is not None:
            setter.argtypes, setter.restype = [ctypes.c_int], None
            getter.argtypes, getter.restype = [], ctypes.c_int
            return setter, getter
    return None


def _loaded_controls() -> list[tuple[Callable[[int], None], Callable[[], int]]]:
    return [found for found in map(_controls, openblas_libraries()) if found is not None]


def set_one_blas_thread() -> int:
    """Set every OpenBLAS library loaded in this process to one thread; return how many."""
    controls = _loaded_controls()
    for setter, _ in controls:
        setter(1)
    return len(controls)


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[int]:
    """
    Run the block with one OpenBLAS thread; yield the number of libraries set.

    The previous thread count of each library is restored on exit, also
    when the block raises.
    """
    previous = [(setter, getter()) for setter, getter in _loaded_controls()]
    for setter, _ in previous:
        setter(1)
    try:
        yield len(previous)
    finally:
        for setter, count in previous:
            setter(count)


__all__ = ['openblas_libraries', 'set_one_blas_thread', 'single_threaded_blas']
