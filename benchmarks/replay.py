"""
Offline replay throughput: whole `bcid replay --json` processes over the committed bags.

Throughput is samples / wall time of the process, start-up (Python, numpy, scipy, mcap
imports) included, so it understates the steady-state rate on a bag of 10,000 samples; the
note gives the start-up time of `bcid --help` measured in the same run for scale.
"""

from __future__ import annotations

import json
from pathlib import Path
import subprocess
import sys
import time

from benchmarks.common import Result

SECTION = 'offline replay throughput'
ROOT = Path(__file__).resolve().parent.parent


def timed(command: list[str], repeats: int) -> tuple[float, subprocess.CompletedProcess]:
    """Run ``command`` ``repeats`` times; return the fastest wall time and the last result."""
    best = float('inf')
    for _ in range(repeats):
        start = time.perf_counter()
        result = subprocess.run(command, capture_output=True, text=True)
        best = min(best, time.perf_counter() - start)
    return best, result


def run(quick: bool = False) -> list[Result]:
    """Replay every committed bag with its scenario's estimator (and rls, bcrls on Ding's)."""
    bcid = str(Path(sys.executable).parent / 'bcid')
    repeats = 1 if quick else 3
    startup, _ = timed([bcid, '--help'], repeats)
    rows = [Result(SECTION, 'start-up of `bcid --help`', startup, 's')]
    for bag in sorted(p.parent for p in (ROOT / 'bags').glob('*/metadata.yaml')):
        config = ROOT / 'config' / f'{bag.name}.yaml'
        estimators = ['rls', 'bcrls'] if bag.name.startswith('ding') else [None]
        for estimator in estimators:
            command = [bcid, 'replay', str(bag), '--params', str(config), '--json']
            if estimator:
                command += ['--estimator', estimator]
            wall, result = timed(command, repeats)
            if result.returncode != 0:
                rows.append(Result(SECTION, f'{bag.name}', float('nan'), 'samples/s',
                                   note=f'FAILED: {result.stderr.strip()[-200:]}'))
                continue
            summary = json.loads(result.stdout)
            rate = summary['samples'] / wall
            target = '≥ 50,000' if summary['estimator'] in ('rls', 'bcrls') else ''
            rows.append(Result(SECTION, f'{summary["estimator"]} on bags/{bag.name}', rate,
                               'samples/s', target, (rate >= 50000) if target else None,
                               note=f'{summary["samples"]} samples in {wall:.3f} s'))
    return rows
