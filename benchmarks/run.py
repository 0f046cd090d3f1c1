"""
Run the benchmarks and write docs/PERFORMANCE.md.

Usage: ``.venv/bin/python -m benchmarks.run [--quick] [--only SECTION ...]`` from the
repository root (``make bench`` does this after installing the benchmark-only peers).
Each section quotes ratios measured in the same run, because these machines are noisy.
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import os
from pathlib import Path
import platform
import sys

from bcid_ros.markdown import markdown_table

ROOT = Path(__file__).resolve().parent.parent
SECTIONS = ('estimators', 'replay', 'csv_logs', 'bag_flips', 'node', 'reproduce', 'pem')


def machine() -> str:
    """Describe the machine in one line."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.startswith('model name'):
                cpu = line.split(':', 1)[1].strip()
                break
    except OSError:
        pass
    return (f'{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, '
            f'{platform.system()} {platform.release()}')


def main(argv: list[str] | None = None) -> int:
    """Run the chosen sections and write the report."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--quick', action='store_true', help='smaller sizes, for a smoke run')
    parser.add_argument('--only', nargs='+', choices=SECTIONS, default=list(SECTIONS))
    parser.add_argument('--out', type=Path, default=ROOT / 'docs' / 'PERFORMANCE.md')
    args = parser.parse_args(argv)
    command = 'python -m benchmarks.run' + (' --quick' if args.quick else '') + (
        f' --only {" ".join(args.only)}' if args.only != list(SECTIONS) else '')
    parts = [
        '# Performance\n',
        f'Measured {datetime.date.today().isoformat()} on {machine()}, with `{command}` '
        '(`make bench`). Every ratio compares figures measured in the same run.\n',
    ]
    for name in args.only:
        module = importlib.import_module(f'benchmarks.{name}')
        print(f'== {name}', file=sys.stderr, flush=True)
        rows = module.run(quick=args.quick)
        for row in rows:
            print(f'{row.metric}: {row.value:.4g} {row.unit} {row.target} '
                  f'{"" if row.met is None else ("met" if row.met else "MISSED")}',
                  file=sys.stderr, flush=True)
        parts.append(f'## {module.SECTION}\n')
        parts.append((module.__doc__ or '').strip() + '\n')
        parts.append(markdown_table(('metric', 'value', 'target', '', 'note'),
                                    [row.cells() for row in rows]))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text('\n'.join(parts))
    print(f'wrote {args.out}', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
