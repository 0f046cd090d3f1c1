"""
Offline replay throughput: whole `bcid replay --json` processes, start-up included.

Three figures, each the fastest of the repeats (another process on this shared machine only
ever makes a run slower):

* start-up: `bcid replay --json` of a 20-sample bag, which is the interpreter, the imports and
  opening a bag; `python -c "import numpy"` in the same run for scale;
* every committed bag with its scenario's estimator (and rls, bcrls on Ding's);
* a 10⁶-sample Ding MISO bag written by `bcid simulate` into a temporary directory (one sample
  per message, as the simulator node publishes), with rls and bcrls.

Throughput is samples / wall time of the process. The note gives the process's CPU time (user +
system) and the estimator's bare update rate (a Python loop of `update_trusted` over the same
samples in this process, in the same run): the replay cannot be faster than that, and on a
loaded machine the CPU figure shows what the wall time hides.
"""

from __future__ import annotations

import json
from pathlib import Path
import resource
import subprocess
import sys
import tempfile
import time

from benchmarks.common import Result

SECTION = 'offline replay throughput'
ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / 'config' / 'ding_miso.yaml'
#: Samples of the large bag (and of the quick run's).
LARGE, LARGE_QUICK = 1_000_000, 100_000


def timed(command: list[str], repeats: int) -> tuple[float, float, subprocess.CompletedProcess]:
    """Run ``command`` ``repeats`` times; return the best wall time, its CPU time, the result."""
    best, best_cpu, result = float('inf'), float('nan'), None
    for _ in range(repeats):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        start = time.perf_counter()
        result = subprocess.run(command, capture_output=True, text=True)
        wall = time.perf_counter() - start
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if wall < best:
            best = wall
            best_cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return best, best_cpu, result


def bare_update_rate(estimator: str, samples: int = 100_000) -> float:
    """Return the samples/s of a bare ``update_trusted`` loop over Ding MISO samples."""
    import numpy as np

    from bcid_ros.parameters import estimator_from_parameters, load_yaml_parameters
    from bcid_ros.simulation import make_scenario

    y, u = make_scenario('ding_miso').simulate(samples, 3)
    values = {**load_yaml_parameters(CONFIG), 'estimator': estimator}
    best = float('inf')
    for _ in range(3):
        update = estimator_from_parameters(values).update_trusted
        outputs, inputs = y.tolist(), list(np.asarray(u, dtype=float))
        start = time.perf_counter()
        for k, value in enumerate(outputs):
            update(value, inputs[k])
        best = min(best, time.perf_counter() - start)
    return samples / best


def replay_row(bcid: str, bag: Path, label: str, config: Path, estimator: str | None,
               repeats: int, target: float | None, bare: dict[str, float]) -> Result:
    """Replay ``bag`` in a fresh process; return its throughput row."""
    command = [bcid, 'replay', str(bag), '--params', str(config), '--json']
    if estimator:
        command += ['--estimator', estimator]
    wall, cpu, result = timed(command, repeats)
    if result.returncode != 0:
        return Result(SECTION, label, float('nan'), 'samples/s',
                      note=f'FAILED: {result.stderr.strip()[-200:]}')
    summary = json.loads(result.stdout)
    name, samples = summary['estimator'], summary['samples']
    rate = samples / wall
    note = f'{samples:,} samples in {wall:.2f} s; CPU {cpu:.2f} s ({samples / cpu:,.0f}/s)'
    if name in bare:
        note += f'; bare update {bare[name]:,.0f}/s'
    return Result(SECTION, f'{name} on {label}', rate, 'samples/s',
                  f'≥ {target:,.0f}' if target else '',
                  (rate >= target) if target else None, note=note)


def simulate(bcid: str, out: Path, samples: int) -> Path:
    """Write a Ding MISO bag of ``samples`` one-sample messages with `bcid simulate`."""
    subprocess.run([bcid, 'simulate', '--scenario', 'ding_miso', '--samples', str(samples),
                    '--seed', '3', '--rate', '1000', '--out', str(out)], check=True,
                   capture_output=True)
    return out


def run(quick: bool = False) -> list[Result]:
    """Measure start-up, the committed bags and a 10⁶-sample bag."""
    bcid = str(Path(sys.executable).parent / 'bcid')
    repeats = 1 if quick else 3
    bare = {name: bare_update_rate(name) for name in ('rls', 'bcrls')}
    rows = []
    with tempfile.TemporaryDirectory() as directory:
        tiny = simulate(bcid, Path(directory) / 'tiny', 20)
        startup, cpu, _ = timed([bcid, 'replay', str(tiny), '--params', str(CONFIG), '--json'],
                                repeats)
        numpy_startup, _, _ = timed([sys.executable, '-c', 'import numpy'], repeats)
        rows.append(Result(SECTION, 'start-up: `bcid replay --json` of a 20-sample bag',
                           startup, 's', '≤ 0.25 s', startup <= 0.25,
                           note=f'CPU {cpu:.3f} s; `python -c "import numpy"` '
                           f'{numpy_startup:.3f} s'))
        for bag in sorted(p.parent for p in (ROOT / 'bags').glob('*/metadata.yaml')):
            config = ROOT / 'config' / f'{bag.name}.yaml'
            ding = bag.name.startswith('ding')
            for estimator in (['rls', 'bcrls'] if ding else [None]):
                rows.append(replay_row(bcid, bag, f'bags/{bag.name}', config, estimator, repeats,
                                       20000 if ding else None, bare))
        large = LARGE_QUICK if quick else LARGE
        big = simulate(bcid, Path(directory) / f'ding_miso_{large}', large)
        for estimator in ('rls', 'bcrls'):
            rows.append(replay_row(bcid, big, f'a {large:,}-sample bag', CONFIG, estimator, 1,
                                   50000, bare))
    return rows
