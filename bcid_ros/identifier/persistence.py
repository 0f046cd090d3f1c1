"""
The identifier's state file: save it atomically, load it only when it fits (pure Python).

A state file lets ``identifier_node`` restart where it stopped (the
``state_file`` parameter, docs/nodes.md "Beside a real plant"). It holds
every number that the next estimates depend on, in named *sections*: the
estimator's snapshot (:meth:`~bcid_ros.estimators.base.RecursiveEstimator.get_state`,
regressor contents, signal scales and flags included) and the
:class:`~bcid_ros.identifier.feeder.SampleFeeder`'s own counters and input history.
Restored into an estimator and a feeder of the same configuration, the
next samples give the same estimates as if there had been no restart.

**Format.** A numpy ``.npz`` archive (a zip of ``.npy`` arrays):

* ``header``: a unicode string holding one JSON object with the format
  name, the format :data:`VERSION`, the configuration fingerprint
  (:func:`configuration_fingerprint`), and per section its scalars and the
  names of its arrays;
* ``<section>.<name>``: each array, in its own dtype and shape.

It is read with ``numpy.load(..., allow_pickle=False)``, so loading never
runs code: the archive can only yield plain arrays and the JSON header
plain numbers, strings, lists and dicts (a pickle, by contrast, executes
whatever it holds). The zip keeps a CRC-32 of every member, so a truncated
or damaged file is detected, not loaded. Floats keep every bit: the arrays
are stored raw, and JSON writes a float as its shortest round-trip repr.

**Atomic saving.** The file is written to a temporary file in the same
directory, flushed and ``fsync``-ed, then moved over the old one with
``os.replace`` (atomic on POSIX); the directory is synced after it. A crash
at any moment leaves either the old file or the new one, never a mix. The
temporary files that a crash leaves (``.<file>.*.tmp``) are removed at the next
start (:func:`remove_leftovers`).

**Nothing overwritten, one writer** (docs/guarantees.md). A file that is
refused is moved aside to ``<file>.rejected-<UTC time>`` (:func:`set_aside`)
before anything is saved over it. :class:`StateLock` holds an ``fcntl`` lock
on ``<file>.lock`` for the life of the process, so a second process given the
same file is refused at start instead of replacing the first one's state.

**Values.** Restoring checks the numbers, not only the shapes
(:func:`check_values`): every array has the dtype of the estimator's own, every
count is >= 0, every value is finite (except where the estimator itself keeps
a NaN for "not computed yet"), and the covariance is symmetric positive definite.
"""

from __future__ import annotations

import datetime
import fcntl
import inspect
import json
import math
import os
from pathlib import Path
import tempfile
from typing import Any

import numpy as np

from bcid_ros.estimators import estimator_class, EstimatorState, RecursiveEstimator
from bcid_ros.estimators.registry import entry
from bcid_ros.identifier.feeder import SampleFeeder

#: The ``format`` field of the header.
FORMAT = 'bcid_ros identifier state'
#: The format version this module writes and reads. A file of a newer
#: version is refused (it may hold state that this version would drop).
VERSION = 1

#: Identifier parameters that fix the meaning of the state's numbers: a state
#: saved under other values is refused. The estimator's own options
#: (``iv_lag``, ``window``, ...) are added per estimator. Live parameters
#: (``forgetting_factor``, ``publish_period``, ...) and the transport
#: (topics, pairing) are not part of it: their values at start-up apply to
#: the restored state.
STRUCTURAL = ('estimator', 'order', 'num_inputs', 'feedthrough', 'initial_covariance',
              'input_delay', 'detrend')

#: One section of a state: ``(arrays, scalars)``.
Section = tuple[dict[str, np.ndarray], dict[str, Any]]


class StateRefused(Exception):
    """
    A state file that cannot be restored; ``str()`` is the one line to log.

    Raised for a file from another configuration, of another format or a
    newer version, or that is truncated or damaged.
    """


def configuration_fingerprint(settings: dict[str, Any]) -> dict[str, Any]:
    """
    Return the settings that a state file must match, as plain JSON values.

    Parameters
    ----------
    settings : dict
        Checked identifier parameters
        (:func:`bcid_ros.identifier.parameters.check_identifier_parameters`).

    Returns
    -------
    dict
        The :data:`STRUCTURAL` parameters present in ``settings`` and the
        estimator's own options; an option left unset takes the
        estimator's default, so that setting it to that default does not
        refuse a state.

    """
    cls = estimator_class(settings['estimator'])
    signature = inspect.signature(cls)
    fingerprint = {name: settings[name] for name in STRUCTURAL if name in settings}
    for name in entry(settings['estimator']).option_names:
        value = settings.get(name)
        if value is None and name in signature.parameters:
            value = signature.parameters[name].default
            value = None if value is inspect.Parameter.empty else value
        fingerprint[name] = value
    return json.loads(_to_json(fingerprint))


def estimator_section(estimator: RecursiveEstimator) -> Section:
    """Return the estimator's full state as a section (see :func:`save_state`)."""
    state = estimator.get_state()
    return state.arrays, dict(state.scalars, estimator=state.estimator)


def restore_estimator(estimator: RecursiveEstimator, section: Section) -> None:
    """
    Restore an estimator from a section made by :func:`estimator_section`.

    Raises
    ------
    ValueError
        If the section is from another estimator or other dimensions.

    """
    arrays, scalars = section
    scalars = dict(scalars)
    name = scalars.pop('estimator', None)
    estimator.set_state(EstimatorState(name, arrays, scalars))


def identifier_sections(estimator: RecursiveEstimator, feeder: SampleFeeder
                        ) -> dict[str, Section]:
    """Return an identifier's state as sections: its estimator's and its feeder's."""
    return {'estimator': estimator_section(estimator), 'feeder': ({}, feeder.get_state())}


def restore_identifier(estimator: RecursiveEstimator, feeder: SampleFeeder,
                       sections: dict[str, Section], forgetting_factor: float,
                       path: str | os.PathLike) -> None:
    """
    Restore an estimator and its feeder from :func:`identifier_sections`, or neither.

    A half-restored identifier is worse than a fresh one: if any section does
    not fit, both go back to where they were (the estimator to its reset).

    Parameters
    ----------
    estimator : RecursiveEstimator
        Restored in place.
    feeder : SampleFeeder
        Restored in place.
    sections : dict
        As :func:`load_state` returns them.
    forgetting_factor : float
        The value the node starts with: a live parameter, so it applies to
        the restored state as it would without one.
    path : str or os.PathLike
        The state file, for the message.

    Raises
    ------
    StateRefused
        If a section is missing or does not fit this estimator or feeder.

    """
    fresh = feeder.get_state()
    estimator.reset()  # set_state replaces all of it; the reset state is the reference
    reference = estimator_section(estimator)
    try:
        check_values(sections['estimator'], reference, 'estimator')
        check_values(({}, sections['feeder'][1]), ({}, fresh), 'feeder')
        restore_estimator(estimator, sections['estimator'])
        feeder.set_state(sections['feeder'][1])
        estimator.forgetting_factor = forgetting_factor
    except Exception as error:  # a missing key, a shape, a value the estimator refuses
        estimator.reset()
        feeder.set_state(fresh)
        raise StateRefused(f'state file {path} does not fit this estimator '
                           f'({type(error).__name__}: {error})') from None


#: Arrays of an estimator's state that are covariance matrices (symmetric positive definite).
COVARIANCES = ('p',)


def check_values(section: Section, reference: Section, name: str) -> None:
    """
    Check the values of a saved section against a fresh one of the same estimator or feeder.

    Parameters
    ----------
    section : (arrays, scalars)
        As loaded.
    reference : (arrays, scalars)
        The same section of a freshly built estimator (or feeder): the dtypes
        and kinds of value expected, and where a non-finite value or a
        negative count is normal.
    name : str
        The section's name, for the message.

    Raises
    ------
    ValueError
        Naming the value: an array of another dtype, a non-finite number, a
        negative count, a value of another type, a covariance that is not
        symmetric positive definite.

    """
    arrays, scalars = section
    expected_arrays, expected_scalars = reference
    for key, value in arrays.items():
        expected = expected_arrays.get(key)
        if expected is None:
            continue  # set_state says what it makes of an unknown key
        value = np.asarray(value)
        if value.dtype != np.asarray(expected).dtype:
            raise ValueError(f'{name}.{key} has dtype {value.dtype}, expected '
                             f'{np.asarray(expected).dtype}')
        if value.dtype.kind == 'f' and not _may_be_nonfinite(expected) \
                and not np.isfinite(value).all():
            raise ValueError(f'{name}.{key} holds NaN or Inf')
        if value.dtype.kind in 'iu' and np.any(value < 0) and not np.any(expected < 0):
            raise ValueError(f'{name}.{key} holds a negative count')
        if key in COVARIANCES:
            _check_covariance(value, f'{name}.{key}')
    for key, value in scalars.items():
        if key in expected_scalars:
            _check_scalar(value, expected_scalars[key], f'{name}.{key}')


def _may_be_nonfinite(expected: Any) -> bool:
    """Whether the fresh value holds a non-finite number (the estimator's "not yet")."""
    if isinstance(expected, np.ndarray):
        return expected.dtype.kind == 'f' and not np.isfinite(expected).all()
    return isinstance(expected, float) and not math.isfinite(expected)


def _check_scalar(value: Any, expected: Any, name: str) -> None:
    """Check one saved scalar (recursively) against the fresh one."""
    if isinstance(expected, (bool, np.bool_)):
        if not isinstance(value, bool):
            raise ValueError(f'{name} is {value!r}, expected true or false')
    elif isinstance(expected, (int, float, np.integer, np.floating)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f'{name} is {value!r}, expected a number')
        if isinstance(value, float) and not math.isfinite(value) \
                and not _may_be_nonfinite(float(expected)):
            raise ValueError(f'{name} is {value!r}, expected a finite number')
        if isinstance(value, int) and isinstance(expected, (int, np.integer)) \
                and value < 0 <= expected:
            raise ValueError(f'{name} is {value}, expected a count >= 0')
    elif isinstance(expected, str):
        if not isinstance(value, str):
            raise ValueError(f'{name} is {value!r}, expected a string')
    elif isinstance(expected, (list, tuple)) and isinstance(value, (list, tuple)):
        if expected and all(not isinstance(e, (list, tuple, dict)) for e in expected):
            for item in value:
                _check_scalar(item, expected[0], name)
    elif isinstance(expected, dict) and isinstance(value, dict):
        for key, item in value.items():
            if key in expected:
                _check_scalar(item, expected[key], f'{name}.{key}')


def _check_covariance(matrix: np.ndarray, name: str) -> None:
    """Check that a covariance matrix is symmetric and positive definite (Cholesky)."""
    if matrix.ndim != 2 or matrix.shape[0] != matrix.shape[1]:
        raise ValueError(f'{name} is not a square matrix (shape {matrix.shape})')
    scale = float(np.max(np.abs(matrix))) if matrix.size else 0.0
    if np.max(np.abs(matrix - matrix.T), initial=0.0) > 1e-8 * scale:
        raise ValueError(f'{name} is not symmetric')
    try:
        np.linalg.cholesky(matrix)
    except np.linalg.LinAlgError:
        raise ValueError(f'{name} is not positive definite') from None


def set_aside(path: str | os.PathLike) -> Path:
    """
    Move a refused state file to ``<file>.rejected-<UTC time>`` so that no save replaces it.

    Returns
    -------
    pathlib.Path
        Where it is now.

    Raises
    ------
    OSError
        If it cannot be moved (the caller must then not save over it).

    """
    path = Path(path)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%dT%H%M%SZ')
    target = path.with_name(f'{path.name}.rejected-{stamp}')
    number = 1
    while target.exists():
        number += 1
        target = path.with_name(f'{path.name}.rejected-{stamp}-{number}')
    os.rename(path, target)
    _sync_directory(path.parent)
    return target


def remove_leftovers(path: str | os.PathLike) -> list[Path]:
    """Remove the temporary files that an interrupted :func:`save_state` left; return them."""
    path = Path(path)
    removed = []
    for leftover in path.parent.glob(f'.{path.name}.*.tmp'):
        try:
            leftover.unlink()
        except OSError:
            continue
        removed.append(leftover)
    return removed


class StateInUse(Exception):
    """Another process holds the state file's lock; ``str()`` is the one line to report."""


class StateLock:
    """
    An exclusive ``fcntl`` lock on ``<file>.lock``, held until :meth:`release` or exit.

    The lock file holds the owner's process id, for the message. The kernel
    drops the lock when the process dies, however it dies.

    Raises
    ------
    StateInUse
        If another process holds it.
    OSError
        If the lock file cannot be created.

    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(f'{os.fspath(path)}.lock')
        descriptor = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = os.read(descriptor, 32).decode('ascii', 'replace').strip() or 'unknown'
            os.close(descriptor)
            raise StateInUse(f'state file {path} is in use by another process (pid {owner}, '
                             f'lock {self.path}); give each identifier its own '
                             'state_file') from None
        os.ftruncate(descriptor, 0)
        os.write(descriptor, f'{os.getpid()}\n'.encode('ascii'))
        self._descriptor: int | None = descriptor

    def release(self) -> None:
        """Drop the lock (idempotent)."""
        if self._descriptor is not None:
            os.close(self._descriptor)
            self._descriptor = None


def save_state(path: str | os.PathLike, fingerprint: dict[str, Any],
               sections: dict[str, Section]) -> None:
    """
    Write the state atomically: a temporary file in the same directory, fsync, rename.

    Parameters
    ----------
    path : str or path-like
        The state file. Its directory must exist.
    fingerprint : dict
        :func:`configuration_fingerprint` of the configuration.
    sections : dict of str to (arrays, scalars)
        The state by section name (``'estimator'``, ``'feeder'``, ...);
        scalars are numbers, strings, booleans, None, and lists, tuples and
        dicts of them. Names must not contain a dot.

    Raises
    ------
    OSError
        If the file cannot be written; the old file, if any, is left intact.

    """
    path = Path(path)
    header = {'format': FORMAT, 'version': VERSION,
              'saved_at': datetime.datetime.now(datetime.timezone.utc).isoformat(),
              'fingerprint': fingerprint, 'sections': {}}
    members: dict[str, np.ndarray] = {}
    for section, (arrays, scalars) in sections.items():
        header['sections'][section] = {'scalars': scalars, 'arrays': sorted(arrays)}
        for key, value in arrays.items():
            members[f'{section}.{key}'] = np.asarray(value)
    members['header'] = np.array(_to_json(header))
    descriptor, temporary = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp',
                                             dir=path.parent)
    try:
        with os.fdopen(descriptor, 'wb') as stream:
            np.savez(stream, **members)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    _sync_directory(path.parent)


def load_state(path: str | os.PathLike, fingerprint: dict[str, Any]) -> dict[str, Section] | None:
    """
    Read a state file saved by :func:`save_state` if it matches ``fingerprint``.

    Parameters
    ----------
    path : str or path-like
        The state file.
    fingerprint : dict
        :func:`configuration_fingerprint` of the current configuration.

    Returns
    -------
    dict of str to (arrays, scalars) or None
        The sections; None if there is no file at ``path`` (a first start).

    Raises
    ------
    StateRefused
        If the file cannot be read, is not a state file, is truncated or
        damaged, is of a newer format version, or comes from another
        configuration. The
        message is one line that says which and names the file.

    """
    path = Path(path)
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as archive:
            header = _read_header(archive)
            _check_header(header, fingerprint)
            sections = {}
            for section, content in header['sections'].items():
                arrays = {key: archive[f'{section}.{key}'] for key in content['arrays']}
                sections[section] = (arrays, dict(content['scalars']))
    except StateRefused as error:
        raise StateRefused(f'state file {path} {error}') from None
    except OSError as error:  # a directory, no permission, an I/O error
        raise StateRefused(f'state file {path} cannot be read ({error})') from None
    except Exception as error:  # zip, npy, JSON and key errors: a damaged file
        raise StateRefused(f'state file {path} is truncated or damaged '
                           f'({type(error).__name__}: {error})') from None
    return sections


def _read_header(archive: Any) -> dict[str, Any]:
    if 'header' not in archive.files:
        raise StateRefused('is not a bcid_ros state file (no header)')
    header = json.loads(str(archive['header'][()]))
    if not isinstance(header, dict) or header.get('format') != FORMAT:
        raise StateRefused('is not a bcid_ros state file')
    return header


def _check_header(header: dict[str, Any], fingerprint: dict[str, Any]) -> None:
    version = header.get('version')
    if type(version) is not int or version < 1:
        raise StateRefused(f'has format version {version!r}, not a version number')
    if version > VERSION:
        raise StateRefused(f'has format version {version!r}, newer than this bcid_ros reads '
                           f'({VERSION})')
    saved = header.get('fingerprint')
    if saved != fingerprint:
        saved = saved if isinstance(saved, dict) else {}
        differences = [f'{name} {saved.get(name, "unset")!r} there, '
                       f'{fingerprint.get(name, "unset")!r} here'
                       for name in sorted(set(saved) | set(fingerprint))
                       if saved.get(name) != fingerprint.get(name)]
        raise StateRefused('is from another configuration (' + '; '.join(differences) + ')')


def _sync_directory(directory: Path) -> None:
    """Make the rename durable; some file systems cannot sync a directory (ignored)."""
    try:
        descriptor = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(descriptor)
    except OSError:
        pass
    finally:
        os.close(descriptor)


def _plain(value: Any) -> Any:
    """Turn numpy scalars into Python ones for JSON (others are a bug: TypeError)."""
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f'state scalar of type {type(value).__name__} cannot be saved')


def _to_json(value: Any) -> str:
    return json.dumps(value, default=_plain, sort_keys=True)


__all__ = ['COVARIANCES', 'FORMAT', 'STRUCTURAL', 'Section', 'StateInUse', 'StateLock',
           'StateRefused', 'VERSION', 'check_values', 'configuration_fingerprint',
           'estimator_section', 'identifier_sections', 'load_state', 'remove_leftovers',
           'restore_estimator', 'restore_identifier', 'save_state', 'set_aside']
