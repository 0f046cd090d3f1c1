"""
Byte flips of a committed bag: an error or the unchanged result, never another one (SPEC §18).

Flips one random bit of one random byte of `bags/ding_miso` (seeded), 80 times, and replays
each copy with `bcid replay --json` in this process. Counts the outcomes: an error (exit code
1), the unchanged JSON, or a changed JSON with exit code 0 (the failure this guards against).
`test/bag/test_bag_integrity.py` runs 24 such flips; this runs the 80 of the issue.
"""

from __future__ import annotations

import collections
import contextlib
import io
from pathlib import Path
import random
import shutil
import sys
import tempfile

from benchmarks.common import Result

SECTION = 'Bag integrity'
ROOT = Path(__file__).resolve().parent.parent
FLIPS, SEED = 80, 80


def replay_json(bag: Path) -> tuple[int, str]:
    """Return the exit code and stdout of `bcid replay BAG --json` run in this process."""
    from bcid_ros.cli import main as bcid

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = bcid(['replay', str(bag), '--params', str(ROOT / 'config/ding_miso.yaml'),
                     '--json'])
    return code, out.getvalue()


def run(quick: bool = False) -> list[Result]:
    """Flip FLIPS random bytes of bags/ding_miso, one at a time; count the outcomes."""
    source = ROOT / 'bags' / 'ding_miso'
    mcap = next(source.glob('*.mcap'))
    data = mcap.read_bytes()
    code, reference = replay_json(source)
    if code:
        raise RuntimeError('the committed bag does not replay')
    rng = random.Random(SEED)
    outcomes: collections.Counter[str] = collections.Counter()
    with tempfile.TemporaryDirectory() as directory:
        bag = Path(directory) / 'ding_miso'
        shutil.copytree(source, bag)
        target = bag / mcap.name
        for _ in range(FLIPS // 4 if quick else FLIPS):
            flipped = bytearray(data)
            flipped[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
            target.write_bytes(bytes(flipped))
            code, out = replay_json(bag)
            outcomes['error' if code else 'unchanged' if out == reference else 'CHANGED'] += 1
    total = sum(outcomes.values())
    return [Result(SECTION, f'{total} one-byte flips of bags/ding_miso: changed results with '
                   'exit 0', outcomes['CHANGED'], 'flips', '0', outcomes['CHANGED'] == 0,
                   note=f"{outcomes['error']} errors, {outcomes['unchanged']} unchanged")]


if __name__ == '__main__':
    for row in run(quick='--quick' in sys.argv):
        print(' | '.join(row.cells()))
