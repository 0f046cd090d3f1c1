"""
The BLAS level-1/2 kernels of the recursive least-squares step, from scipy.

They are loaded on first use, and without importing all of ``scipy.linalg``
where possible, so that importing an estimator module (and a replay's
start-up) does not pay for scipy.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
from typing import Any

#: BLAS level-1/2 kernels, loaded from scipy on first use (see :func:`load_blas`).
KERNELS: dict[str, Any] = {}


def load_blas() -> dict[str, Any]:
    """
    Return scipy's BLAS kernels daxpy, dgemv, dger and dscal, importing scipy on first call.

    The estimators call it when they are built, so that importing a module
    of this package does not import scipy. The kernels are called with
    positional arguments: f2py parses keywords at a cost comparable to the
    kernel at p = 6.
    """
    if not KERNELS:
        blas = fblas_module()
        KERNELS.update((name, getattr(blas, name)) for name in ('daxpy', 'dgemv', 'dger', 'dscal'))
    return KERNELS


def fblas_module() -> Any:
    """
    Return scipy's compiled BLAS wrappers, loaded without all of ``scipy.linalg`` if possible.

    ``scipy.linalg.blas`` re-exports the f2py extension ``scipy/linalg/_fblas``,
    but importing it runs ``scipy/linalg/__init__.py``, which imports the whole
    of ``scipy.linalg`` and, through scipy's array-API layer, ``numpy.testing``
    and ``numpy.f2py``: 0.17 s, half of a replay's start-up. The extension needs
    only numpy, so until something imports ``scipy.linalg`` it is loaded from
    its file (the same functions, a few ms). A scipy laid out otherwise, or one
    whose extension does not load that way, gets the normal import.
    """
    try:
        return _fblas_from_file()
    except (ImportError, OSError):
        from scipy.linalg import blas
        return blas


def _fblas_from_file() -> Any:
    """Load ``scipy.linalg._fblas`` from its file, without importing ``scipy.linalg``."""
    name = 'scipy.linalg._fblas'
    if name in sys.modules:  # scipy.linalg was imported: take its own
        return sys.modules[name]
    import scipy  # its __init__ prepares the shared libraries where a platform needs it

    for folder in scipy.__path__:
        for suffix in importlib.machinery.EXTENSION_SUFFIXES:
            path = os.path.join(folder, 'linalg', '_fblas' + suffix)
            if os.path.isfile(path):
                loader = importlib.machinery.ExtensionFileLoader(name, path)
                spec = importlib.util.spec_from_file_location(name, path, loader=loader)
                module = importlib.util.module_from_spec(spec)
                loader.exec_module(module)
                return module
    raise ImportError(f'no {name} extension file in {list(scipy.__path__)}')
