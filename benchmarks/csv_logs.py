"""
CSV logs: reading a 10⁶-row CSV, `bcid import` of it, and `bcid replay` of the CSV against the bag.

The CSV is 10⁶ rows of Ding MISO samples (`bcid simulate`'s, seed 3) with a time column at
1 kHz, every double written with `repr` (about 70 bytes a row), in a temporary directory.

* reading: `read_csv_samples` in this process with the time column, the fastest of the
  repeats; beside it, reading the same samples from the bag that `bcid import` writes
  (`BagReader.blocks`, one-sample messages), in the same run;
* import: the whole `bcid import --time-column` process;
* replay: whole `bcid replay --json` processes with rls, of the CSV and of the imported bag,
  whose JSON must be equal (the run fails otherwise);
* memory: the peak RSS of `bcid replay --json` of the CSV and of a CSV four times as long
  (the log is streamed: the peak must not grow with the file; SPEC §18: a 1 GB CSV under
  200 MB at >= 100k rows/s). `python -m benchmarks.csv_logs --rows 14700000` runs the 1 GB
  case itself (about 15 minutes on a shared machine, most of it writing the CSV).

Wall times are the fastest of the repeats (another process on this shared machine only ever
makes a run slower); the note gives the ratio of the two figures of one row.
"""

from __future__ import annotations

from pathlib import Path
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.common import Result
from benchmarks.replay import compile_package, simulate, timed

SECTION = 'CSV logs'
ROOT = Path(__file__).resolve().parent.parent
#: Rows of the CSV (and of the quick run's).
ROWS, ROWS_QUICK = 1_000_000, 100_000
#: The read target of docs/bags.md: 10⁶ rows in about a second or two.
READ_TARGET_S = 2.0
#: SPEC §18: peak memory of a streamed CSV replay (MB) and its speed (rows/s).
MEMORY_TARGET_MB, SPEED_TARGET = 200.0, 100_000

PARAMETERS = 'bcid_identifier:\n  ros__parameters:\n    estimator: rls\n    order: 2\n' \
    '    num_inputs: 2\n'


def write_csv(bag: Path, out: Path) -> Path:
    """Write the samples of a bag as a CSV with a time column (seconds) and y,u1,u2."""
    from bcid_ros.bag.reader import BagReader

    blocks = list(BagReader(bag).blocks('/samples'))
    times = np.concatenate([b.times_ns for b in blocks]) / 1e9
    rows = np.vstack([b.data for b in blocks])
    with out.open('w') as stream:
        stream.write('time,y,u1,u2\n')
        stream.writelines(f'{t!r},{y!r},{a!r},{b!r}\n' for t, y, a, b in
                          zip(times.tolist(), *rows.T.tolist()))
    return out


def peak_rss_mb(command: list[str]) -> tuple[float, float]:
    """Return the wall time (s) and peak RSS (MB) of ``command``, run in a wrapper of its own."""
    wrapper = ('import resource, subprocess, sys, time\n'
               'start = time.perf_counter()\n'
               'done = subprocess.run(sys.argv[1:], capture_output=True)\n'
               'wall = time.perf_counter() - start\n'
               'if done.returncode: sys.exit(done.stderr.decode())\n'
               'print(wall, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024)')
    done = subprocess.run([sys.executable, '-c', wrapper, *command], capture_output=True,
                          text=True, check=True)
    wall, peak = done.stdout.split()
    return float(wall), float(peak)


def replay_memory(bcid: str, here: Path, rows: int, parameters: Path) -> list[Result]:
    """Measure the peak RSS of replaying CSVs of ``rows`` and 4 ``rows`` rows (streamed)."""
    figures = []
    for count in (rows, 4 * rows):
        csv = write_csv(simulate(bcid, here / f'memory{count}', count), here / f'm{count}.csv')
        wall, peak = peak_rss_mb([bcid, 'replay', str(csv), '--params', str(parameters),
                                  '--json', '--time-column', 'time'])
        figures.append((count, csv.stat().st_size / 1e6, wall, peak))
        csv.unlink()
    (small, small_mb, _, small_peak), (large, large_mb, wall, peak) = figures
    return [Result(SECTION, f'`bcid replay --json` of a {large:,}-row CSV ({large_mb:.0f} MB): '
                   'peak RSS', peak, 'MB', f'< {MEMORY_TARGET_MB:g} MB, flat',
                   peak < MEMORY_TARGET_MB and peak < 1.2 * small_peak,
                   note=f'{small:,} rows ({small_mb:.0f} MB): {small_peak:.0f} MB; '
                   f'{large / wall:,.0f} rows/s over the whole process')]


def best_seconds(call, repeats: int) -> float:
    """Return the fastest wall time of ``repeats`` calls of ``call``."""
    best = float('inf')
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - start)
    return best


def run(quick: bool = False, memory_rows: int = 0) -> list[Result]:
    """Measure reading, importing and replaying a CSV log; the memory with ``memory_rows``."""
    from bcid_ros.bag.csv_samples import read_csv_samples
    from bcid_ros.bag.reader import BagReader

    bcid = str(Path(sys.executable).parent / 'bcid')
    repeats = 1 if quick else 3
    count = ROWS_QUICK if quick else ROWS
    compile_package()
    rows = []
    with tempfile.TemporaryDirectory() as directory:
        here = Path(directory)
        csv = write_csv(simulate(bcid, here / 'source', count), here / 'log.csv')
        megabytes = csv.stat().st_size / 1e6
        read = best_seconds(lambda: read_csv_samples(csv, time_column='time'), repeats)
        bag = here / 'imported'
        wall, cpu, done = timed([bcid, 'import', str(csv), '--out', str(bag), '--time-column',
                                 'time'], 1)
        if done.returncode:
            raise RuntimeError(done.stderr)
        from_bag = best_seconds(lambda: [b.data for b in BagReader(bag).blocks('/samples')],
                                repeats)
        rows.append(Result(SECTION, f'read a {count:,}-row CSV (time,y,u1,u2; {megabytes:.0f} '
                           'MB)', read, 's', f'≤ {READ_TARGET_S:g} s' if not quick else '',
                           read <= READ_TARGET_S if not quick else None,
                           note=f'{count / read:,.0f} rows/s; the same samples from the '
                           f'imported bag: {from_bag:.3g} s (CSV / bag = {read / from_bag:.1f})'))
        rows.append(Result(SECTION, '`bcid import` of it', wall, 's',
                           note=f'CPU {cpu:.3g} s; {count / wall:,.0f} rows/s'))
        parameters = here / 'rls.yaml'
        parameters.write_text(PARAMETERS)
        figures = {}
        for label, source, options in (('CSV', csv, ['--time-column', 'time']),
                                       ('imported bag', bag, [])):
            wall, cpu, done = timed([bcid, 'replay', str(source), '--params', str(parameters),
                                     '--json', *options], repeats)
            if done.returncode:
                raise RuntimeError(done.stderr)
            figures[label] = (wall, done.stdout)
        if figures['CSV'][1] != figures['imported bag'][1]:
            raise RuntimeError('the replay of the CSV and of its imported bag differ')
        csv_wall, bag_wall = figures['CSV'][0], figures['imported bag'][0]
        rows.append(Result(SECTION, '`bcid replay --json` (rls) of the CSV', csv_wall, 's',
                           note=f'of the imported bag: {bag_wall:.3g} s (CSV / bag = '
                           f'{csv_wall / bag_wall:.2f}); equal JSON; {count / csv_wall:,.0f} '
                           'rows/s'))
        rows += replay_memory(bcid, here, memory_rows or count, parameters)
    return rows


if __name__ == '__main__':
    large = int(sys.argv[sys.argv.index('--rows') + 1]) // 4 if '--rows' in sys.argv else 0
    for row in run(quick='--quick' in sys.argv, memory_rows=large):
        print(' | '.join(row.cells()))
