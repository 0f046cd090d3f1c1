"""
Wall time of the paper reproductions, whole `bcid reproduce` processes.

The paper's own figure for Ikeda (2008) is the CPU time of 1000 estimates (32.6 s with bias
compensation, 42.7 s without, on the 2008 author's machine); `bcid reproduce ikeda` also
reports the CPU time of its own 1000 estimates in docs/reproduction_ikeda.md.
"""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys
import tempfile
import time

from benchmarks.common import Result

SECTION = 'reproduction wall time'


def run(quick: bool = False) -> list[Result]:
    """Time `bcid reproduce <paper>` for each paper (full size unless quick)."""
    bcid = Path(sys.executable).parent / 'bcid'
    rows = []
    for paper in ('ding', 'ikenoue', 'ikeda'):
        with tempfile.TemporaryDirectory() as out:
            command = [str(bcid), 'reproduce', paper, '--out-dir', out] + (
                ['--quick'] if quick else [])
            start = time.perf_counter()
            result = subprocess.run(command, capture_output=True, text=True)
            wall = time.perf_counter() - start
        note = ' '.join(command[1:3]) + (' --quick' if quick else ' (full size)')
        if result.returncode != 0:
            note += f'; FAILED: {result.stderr.strip().splitlines()[-1:]}'
        target = 'paper: 32.6 s CPU for 1000 estimates' if paper == 'ikeda' else ''
        rows.append(Result(SECTION, f'bcid reproduce {paper}', wall, 's', target, None, note))
    return rows
