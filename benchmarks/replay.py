"""
Offline replay throughput: whole `bcid replay --json` processes, start-up included.

Three figures, each the fastest of the repeats (another process on this shared machine only
ever makes a run slower):

* start-up: `bcid replay --json` of a 20-sample bag, which is the interpreter, the imports and
  opening a bag; `python -c "import numpy"` in the same run for scale; and the replay's
  imports from `python -X importtime`, grouped by what the process imports itself (a module's
  figure includes what it imports first);
* every committed bag with its scenario's estimator (and rls, bcrls on Ding's);
* a 10⁶-sample Ding MISO bag written by `bcid simulate` into a temporary directory (one sample
  per message, as the simulator node publishes), with rls and bcrls.

The package is byte-compiled first, as an installed one is: where `PYTHONDONTWRITEBYTECODE`
is set, every process would otherwise compile our modules from source (about 40 ms).
Throughput is samples / wall time of the process. The note gives the process's CPU time (user +
system) and the estimator's bare update rate (a Python loop of `update` over the same
samples in this process, in the same run); a replay of rls or bcrls can beat it, because its
blocks take the estimator's block path (the regressors of a block formed at once). The CPU
figure shows what the wall time hides.
"""

from __future__ import annotations

import json
import os
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
    """Return the samples/s of a bare ``update`` loop over Ding MISO samples."""
    import numpy as np

    from bcid_ros.identifier.parameters import estimator_from_parameters, load_yaml_parameters
    from bcid_ros.simulation import make_scenario

    y, u = make_scenario('ding_miso').simulate(samples, 3)
    values = {**load_yaml_parameters(CONFIG), 'estimator': estimator}
    best = float('inf')
    for _ in range(3):
        update = estimator_from_parameters(values).update
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


def import_profile(command: list[str], repeats: int, top: int = 10) -> tuple[float, str]:
    """
    Return the total of ``command``'s top-level imports (s) and its ``top`` largest, in words.

    ``command`` is a ``python -c`` command line; each module's time is the least over the
    repeats, from ``-X importtime``.
    """
    best: dict[str, int] = {}
    for _ in range(repeats):
        lines = subprocess.run(command[:1] + ['-X', 'importtime'] + command[1:],
                               capture_output=True, text=True).stderr.splitlines()
        for line in lines:
            fields = line.removeprefix('import time:').split('|')
            if len(fields) != 3 or not fields[1].strip().isdigit():
                continue
            name = fields[2]
            if name.startswith(' ') and not name.startswith('  '):  # a top-level import
                name = name.strip()
                best[name] = min(best.get(name, 1 << 62), int(fields[1]))
    ranked = sorted(best.items(), key=lambda item: -item[1])
    words = ', '.join(f'{name} {us / 1000:.0f}' for name, us in ranked[:top])
    return sum(best.values()) / 1e6, f'largest (ms): {words}'


def startup_rows(bcid: str, tiny: Path, repeats: int) -> list[Result]:
    """Start-up, numpy's import for scale, and the import profile."""
    replay = ['replay', str(tiny), '--params', str(CONFIG), '--json']
    startup, cpu, _ = timed([bcid] + replay, repeats)
    numpy_startup, numpy_cpu, _ = timed([sys.executable, '-c', 'import numpy'], repeats)
    rows = [Result(SECTION, 'start-up: `bcid replay --json` of a 20-sample bag', startup, 's',
                   '≤ 0.25 s', startup <= 0.25,
                   note=f'CPU {cpu:.3f} s; `python -c "import numpy"` {numpy_startup:.3f} s '
                   f'(CPU {numpy_cpu:.3f} s)')]
    code = 'import sys; from bcid_ros.cli import main; sys.exit(main(sys.argv[1:]))'
    total, words = import_profile([sys.executable, '-c', code] + replay, repeats + 2)
    rows.append(Result(SECTION, 'imports of that replay', total, 's', note=words))
    return rows


def compile_package() -> None:
    """Byte-compile bcid_ros, as an installed package is (see the module docstring)."""
    environment = {k: v for k, v in os.environ.items() if k != 'PYTHONDONTWRITEBYTECODE'}
    subprocess.run([sys.executable, '-m', 'compileall', '-q', str(ROOT / 'bcid_ros')],
                   check=True, capture_output=True, env=environment)


def run(quick: bool = False) -> list[Result]:
    """Measure start-up, the committed bags and a 10⁶-sample bag."""
    bcid = str(Path(sys.executable).parent / 'bcid')
    repeats = 1 if quick else 3
    bare = {name: bare_update_rate(name) for name in ('rls', 'bcrls')}
    compile_package()
    with tempfile.TemporaryDirectory() as directory:
        tiny = simulate(bcid, Path(directory) / 'tiny', 20)
        rows = startup_rows(bcid, tiny, repeats)
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
