"""
Monte Carlo reproductions of the papers' simulation studies (``bcid reproduce``).

Each paper has one module with ``reproduce(runs, quick, out_dir, progress) -> str``,
which writes ``docs/reproduction_<paper>.md`` and its PNG figures and returns
the Markdown it wrote.
"""

from __future__ import annotations

import importlib
from pathlib import Path

PAPERS = ('ding', 'ikenoue', 'ikeda')


def reproduce(which: str, runs: int | None, quick: bool, out_dir: Path) -> list[Path]:
    """Run the study of one paper (or ``'all'``) and return the files written."""
    from bcid_ros.reproduction.common import Progress

    written = []
    for paper in PAPERS if which == 'all' else (which,):
        module = importlib.import_module(f'bcid_ros.reproduction.{paper}')
        written.extend(module.reproduce(runs=runs, quick=quick, out_dir=out_dir,
                                        progress=Progress(paper)))
    return written
