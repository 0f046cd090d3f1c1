"""
Find the package's installed share files (config/) from any install.

The PyPI ROS wheels set no ``AMENT_PREFIX_PATH``, so the ament index is
searched with the interpreter's prefix added; a source checkout (editable
install) falls back to the repository's own ``config/``.
"""

from __future__ import annotations

import os
from pathlib import Path
import sys

PACKAGE = 'bcid_ros'


def share_directory() -> Path:
    """Return the directory that holds ``config/`` for this installation."""
    prefixes = [p for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p]
    prefixes.append(sys.prefix)
    for prefix in prefixes:
        marker = Path(prefix, 'share', 'ament_index', 'resource_index', 'packages', PACKAGE)
        share = Path(prefix, 'share', PACKAGE)
        if marker.is_file() and (share / 'config').is_dir():
            return share
    source_tree = Path(__file__).resolve().parent.parent
    if (source_tree / 'config').is_dir():
        return source_tree
    raise FileNotFoundError(f'cannot find the share directory of {PACKAGE}; '
                            'set AMENT_PREFIX_PATH to its install prefix')


def config_file(name: str) -> Path:
    """Return the path of ``config/<name>`` (``.yaml`` added if missing)."""
    if not name.endswith('.yaml'):
        name += '.yaml'
    path = share_directory() / 'config' / name
    if not path.is_file():
        raise FileNotFoundError(f'no config file {name} in {path.parent}')
    return path
