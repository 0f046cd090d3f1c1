"""
CSV logs: reading a 10⁶-row CSV, `bcid import` of it, and `bcid replay` of the CSV against the bag.

The CSV is 10⁶ rows of Ding MISO samples (`bcid simulate`'s, seed 3) with a time column at
1 kHz, every double written with `repr` (about 70 bytes a row), in a temporary directory.

* reading: `read_csv_samples` in this process with the time column, the fastest of the
  repeats; beside it, reading the same samples from the bag that `bcid import` writes
  (`BagReader.blocks`, one-sample messages), in the same run;
* import: the whole `bcid import --time-column` process;
* replay: whole `bcid replay --json` processes with rls, of the CSV and of the imported bag,
  whose JSON must be equal (the run fails otherwise).

Wall times are the fastest of the repeats (another process on this shared machine only ever
makes a run slower); the note gives the ratio of the two figures of one row.
"""

from __future__ import annotations

from pathlib import Path
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


def best_seconds(call, repeats: int) -> float:
    """Return the fastest wall time of ``repeats`` calls of ``call``."""
    best = float('inf')
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        best = min(best, time.perf_counter() - start)
    return best


def run(quick: bool = False) -> list[Result]:
    """Measure reading, importing and replaying a CSV log."""
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
                           f'{csv_wall / bag_wall:.2f}); equal JSON'))
    return rows


if __name__ == '__main__':
    for row in run(quick='--quick' in sys.argv):
        print(' | '.join(row.cells()))
